"""Built-in drivers (installed as ``aiohal.drivers``). Each is imported only when a config uses it."""
