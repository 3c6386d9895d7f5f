"""Simulation (installed as ``stagectl.sim``): the stage plant and the virtual devices that speak the
real protocols (CANopen CiA 402 drive, CiA 406 encoder, serial interferometer) around it.
"""
