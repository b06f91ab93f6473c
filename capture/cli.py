"""`scanstation` command line: sub-commands, progress on stderr, one-line errors."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import warnings

from . import LOGGERS

#: sub-command modules, imported lazily so `scanstation --help` stays fast.
COMMANDS = ("demo", "scan", "replay", "reprocess", "calibrate", "reconstruct", "remesh",
            "devices", "serve", "simulate")
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (OSError, ValueError)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scanstation",
        description="Scanner-capture workstation: capture depth + turntable scans, build meshes.",
    )
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress output (warnings and errors still)")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug output")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        importlib.import_module(f"capture.commands.{name}").add_parser(subparsers)
    for sub in subparsers.choices.values():  # also after the command: `scanstation scan -q`
        sub.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                         help="no progress output (warnings and errors still)")
        sub.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                         help="debug output, tracebacks")
    return parser


def _setup_output(quiet: bool, verbose: bool) -> None:
    """Progress at INFO (none when ``quiet``, DEBUG when ``verbose``), warnings always, one line
    each."""
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING)
    for name in LOGGERS:
        logging.getLogger(name).setLevel(level)

    def one_line_warning(message, category, filename, lineno, file=None, line=None):
        print(f"warning: {message}", file=sys.stderr)  # even quiet: a result may differ

    warnings.showwarning = one_line_warning


def main(argv: list[str] | None = None) -> int:
    from capture.reprocess import ReprocessError
    from capture.runner import CaptureError
    from drivers.errors import DeviceError
    from reconstruct.errors import ReconstructionError

    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_output(args.quiet, args.verbose)
    try:
        return int(args.run(args) or 0)
    except KeyboardInterrupt:
        print("scanstation: interrupted", file=sys.stderr)
        return 130
    except (ReconstructionError, DeviceError, CaptureError, ReprocessError,
            *EXPECTED_ERRORS) as exc:
        if args.verbose:
            raise
        print(f"scanstation: error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug, a library's failure, MemoryError: still one line
        if args.verbose:
            raise
        print(f"scanstation: error: unexpected {type(exc).__name__}: {exc} (run with -v for "
              "the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
