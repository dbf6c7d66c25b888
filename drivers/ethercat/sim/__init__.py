"""A simulated EtherCAT slave segment (stdlib only).

Real masters (SOEM through pysoem) talk to it over a veth pair: the simulator runs in its own
network namespace and answers raw EtherCAT frames on its end of the pair. Modules, one job each:

* :mod:`.sii` - SII EEPROM images (header words and categories);
* :mod:`.od` - CoE object dictionary, data types, PDO codecs;
* :mod:`.coe` - mailbox protocol and CoE server (SDO, SDO information, emergencies);
* :mod:`.esc` - one ESC: registers, EEPROM interface, AL states, SyncManagers, FMMUs, DC,
  process-data watchdog;
* :mod:`.devices`, :mod:`.drive` - device models (CiA 402 drive, IMU, force/torque, digital I/O);
* :mod:`.segment` - frames and datagrams over a line of slaves, fault injection;
* :mod:`.control` - JSON control commands;
* :mod:`.net` - the raw-socket runner; :mod:`.fixture` - start it in a namespace for tests;
* ``python -m aiohal.drivers.ethercat.sim`` - the command line.

See docs/ethercat.md, section "The simulated segment".
"""

from .control import apply as apply_control
from .devices import DigitalIO, ForceTorque, Imu
from .drive import Drive
from .esc import Esc
from .segment import Segment
from .spec import parse_spec

__all__ = ["DigitalIO", "Drive", "Esc", "ForceTorque", "Imu", "Segment", "apply_control", "parse_spec"]
