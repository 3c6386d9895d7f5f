"""Device drivers (installed as ``stagectl.drivers``): CANopen CiA 402 drive, CiA 406 encoder, serial
interferometer. Every driver implements the ABCs in :mod:`stagectl.drivers.base`; the same driver code
talks to real hardware and to the virtual devices of :mod:`stagectl.sim`.
"""
