"""stagectl: a friction-compensating controller for precision linear stages.

Layers (imports only point down this list; ``tests/test_layers.py`` enforces it):

1. ``stagectl.errors``, ``stagectl.schema``  -- shared foundations
2. ``stagectl.friction``                    -- pure friction math and effects
3. ``stagectl.sim``                         -- stage plant and virtual devices
4. ``stagectl.drivers``                     -- CANopen / serial drivers (same ABC for real and virtual)
5. ``stagectl.control``                     -- pure control laws
6. ``stagectl.loop`` / ``stagectl.app``      -- the fixed-rate loop and its assembly
7. ``stagectl.daemon``, ``stagectl.ident``, ``stagectl.cli`` -- the shell and offline tools
"""

__version__ = "0.1.0"
