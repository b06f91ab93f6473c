"""The live reconstruction of a scan: the merged cloud (`cloud`), the incremental engine
(`engine`), the closed object's patches chosen, fitted and merged as the views arrive
(`patches`, `patch_cache`, `patch_fit`). Imports no device: views arrive as points."""
