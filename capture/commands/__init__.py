"""One module per `scanstation` sub-command: each has `add_parser(subparsers)` and `run(args)`."""
