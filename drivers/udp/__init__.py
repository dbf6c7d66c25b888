"""UDP Ethernet joint boards: the wire format (``protocol``), the ``udp`` driver and the
simulated boards (``python -m aiohal.drivers.udp.sim``). See docs/udp.md."""
