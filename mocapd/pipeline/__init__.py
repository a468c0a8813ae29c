"""Ring buffers, interpolation, the fixed-latency scheduler, detector workers and per-subject solve loops."""
