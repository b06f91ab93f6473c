"""The rooms keep their doors: no import loop inside capture/, and the thread-leak check (every
test's) sees our own daemon threads."""

import threading

import grimp


def test_no_import_loop_in_capture():
    graph = grimp.build_graph("capture")
    loops = []
    for module in sorted(graph.modules):
        for imported in graph.find_modules_directly_imported_by(module):
            back = graph.find_shortest_chain(importer=imported, imported=module)
            if back is not None:
                loops.append((module, *back))
    assert loops == []


def test_leak_check_sees_our_daemon_threads(leaked_threads):
    before = set(threading.enumerate())
    release = threading.Event()
    thread = threading.Thread(target=release.wait, name="scan-runner", daemon=True)
    thread.start()
    try:
        assert [t.name for t in leaked_threads(before)] == ["scan-runner"]
    finally:
        release.set()
        thread.join()
    assert leaked_threads(before) == []
