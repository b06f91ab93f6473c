"""The headless daemon: `scanstation serve` puts the scan runner behind an HTTP API (FastAPI),
live Server-Sent Events, a web page and a restart-safe SQLite job store. Entry point:
`capture.daemon.app.create_app`."""
