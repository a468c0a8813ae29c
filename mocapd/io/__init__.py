"""The I/O edge: thin adapters for cameras, serial ports, sockets and files."""
