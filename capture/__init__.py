"""Capture sessions, the command line and the daemon: composes drivers and reconstruct."""
