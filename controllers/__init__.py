"""Built-in controllers (installed as ``aiohal.controllers``): hold, homing, sine."""
