"""ambhil bridge: zenoh transport, protocol, the plant and controller processes, MCAP recording and replay."""
