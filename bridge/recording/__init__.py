"""ambhil bridge: recording."""
