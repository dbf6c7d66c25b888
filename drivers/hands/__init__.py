"""Non-real-time hand backends (blocking I/O) and the service that puts one behind a pipe.

A backend runs on the NRT side of an ``aiohal.pipe`` (a thread or, by default, a subprocess);
the ``nrt_hand`` driver on the fast side only ever touches the pipe.
"""
