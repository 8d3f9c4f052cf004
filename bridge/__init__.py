"""ambhil bridge: zenoh transport, nodes, MCAP recording and replay."""
