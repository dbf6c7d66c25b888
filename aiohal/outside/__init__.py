"""Everything outside the tick: the doors to other processes and the outputs of a run.

The shared-memory door (``shm``, whose other side is :mod:`aiohal.client`), the Zenoh bridge
(``zenoh``), the recorder and its Foxglove server, the live terminal status, and the command
line's glue for them (``cli_outputs``). None of them runs its work in the tick: the tick only
copies its state for them at its end, and they do the rest in a thread, on the event loop or
in another process.
"""
