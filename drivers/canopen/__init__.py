"""CANopen for aiohal: the driver on python-can and canopen (CiA 402 drives, DBC sensors decoded
with cantools) and, in :mod:`aiohal.drivers.canopen.sim`, simulated nodes on any python-can
interface."""
