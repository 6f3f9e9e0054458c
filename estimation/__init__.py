"""Pure numerical layer: plant models, observers, resilient fusion rules, gain and LMI
design, graph conditions. No asyncio, zenoh, rerun, msgpack or I/O here (a test enforces
that this package imports nothing from ``agents``, ``transport`` or ``scenarios``)."""
