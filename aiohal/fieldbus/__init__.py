"""Code that fieldbus drivers share, apart from the tick core.

* :mod:`aiohal.fieldbus.cia402` – the CiA 402 drive state machine and drive units, for every
  bus that carries CiA 402 drives (EtherCAT CoE, CANopen);
* :mod:`aiohal.fieldbus.drives` – every CiA 402 drive of a bus on its process data (state
  machines, bumpless enable, the compiled conversions);
* :mod:`aiohal.fieldbus.cia402_driver` – the base of the drivers of CiA 402 drives: what they
  do alike on every bus, off the tick (enable, fault reset, estop, shutdown, health);
* :mod:`aiohal.fieldbus.busvar` – bus variables: PDO layouts and process data linked by name.

The EtherCAT, CANopen and UDP drivers import these; the loop and the rest of the core never do.
"""
