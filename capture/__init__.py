"""Capture sessions, the command line and the daemon: composes drivers and reconstruct."""

#: The loggers of ScanStation's packages, whose levels the CLI and a daemon's scan process set
#: for their output.
LOGGERS = ("capture", "reconstruct", "drivers", "sim")
