"""`scanstation devices`: the backends and the devices they can see."""

from __future__ import annotations


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("devices", help="list device backends and visible devices")
    parser.set_defaults(run=run)


def run(args) -> int:
    from drivers.registry import list_devices

    rows = list_devices()
    width = max(len(f"{scheme}://") for _, scheme, _, _ in rows)
    for kind, scheme, status, urls in rows:
        print(f"{kind:<10} {scheme + '://':<{width}}  {status}")
        for url in urls:
            print(f"{'':<10} {'':<{width}}    {url}")
    return 0
