"""EtherCAT for aiohal: the pysoem driver and, in :mod:`aiohal.drivers.ethercat.sim`, a simulated
slave segment (stdlib only) that real SOEM can talk to over a veth pair."""
