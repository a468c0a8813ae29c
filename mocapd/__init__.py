"""mocapd — real-time multi-person motion capture from multi-view video and Xsens IMUs.

Layers (imports only point downward)::

    core/        pure math: rotations, skeleton + kinematics, cameras, cost terms, LM solver, PCA prior
    protocols/   sans-I/O byte protocols (Xbus, stream formats)
    io/          thin adapters: cameras, serial ports, sockets, files
    pipeline/    ring buffers, interpolation, scheduler, detector workers
    service/     config, the asyncio application, HTTP status, CLI
"""

__version__ = "0.1.0"
