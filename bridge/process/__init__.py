"""ambhil bridge: process."""
