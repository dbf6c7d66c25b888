"""The KUKA LWR 4+ over the Fast Research Interface (FRI 1.x, KRC 2lr): the wire format
(``protocol``), the ``fri`` driver (the remote PC's side) and a KRC simulator
(``python -m aiohal.drivers.fri.sim``). See docs/fri.md."""
