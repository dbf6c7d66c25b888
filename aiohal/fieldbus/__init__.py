"""Code that fieldbus drivers share, apart from the tick core.

* :mod:`aiohal.fieldbus.cia402` – the CiA 402 drive state machine and drive units, for every
  bus that carries CiA 402 drives (EtherCAT CoE, CANopen);
* :mod:`aiohal.fieldbus.busvar` – bus variables: PDO layouts and process data linked by name.

The EtherCAT, CANopen and UDP drivers import these; the loop and the rest of the core never do.
"""
