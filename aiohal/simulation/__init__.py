"""Simulation, apart from the tick core: what simulated devices run behind their buses.

* :mod:`aiohal.simulation.servo` – a servo drive (LOLA's cascade with the motor, gear and
  load), plain and compiled; the mock's, the simulated drives' and the simulated joints'
  ``dynamics = "servo"``;
* :mod:`aiohal.simulation.joints` – joint models of simulated bus devices (the UDP boards, the
  KRC): a first-order servo or each joint behind the servo drive;
* :mod:`aiohal.simulation.joint_options` – those joints' options and the simulator's command
  line for them;
* :mod:`aiohal.simulation.process` – a simulator run as a subprocess the driver starts itself;
* :mod:`aiohal.simulation.od` – the object dictionary and PDO codecs of simulated CiA 301
  devices;
* :mod:`aiohal.simulation.cia402_drive` – the simulated CiA 402 drive both bus simulators
  (EtherCAT, CANopen) put behind their own communication.

Drivers and their bus simulators (``drivers/*/sim*``) import these; the loop never does.
"""
