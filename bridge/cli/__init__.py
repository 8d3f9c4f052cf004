"""ambhil bridge: cli."""
