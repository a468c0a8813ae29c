"""Sans-I/O byte protocols: bytes and values in, events and bytes out. No sockets, serial, asyncio or clocks."""
