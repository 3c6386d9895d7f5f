"""stagectl: a friction-compensating controller for precision linear stages.

Layers, lowest first. A module imports only its own rank or lower, never a higher one, and no two modules
import each other; within ranks 2 and 3 the groups are independent of each other. ``tests/test_layers.py``
enforces this for every import form; ``docs/architecture.md`` explains it.

0. foundations  ``stagectl.errors``, ``stagectl.outputs``, ``stagectl.resources``, ``stagectl.clock``
1. schema       ``stagectl.schema``  -- declarative config fields with units and bounds
2. models, I/O  ``stagectl.friction`` (pure friction math, effects, the stage model file) |
                ``stagectl.drivers`` (CANopen / serial drivers on one ABC) | ``stagectl.safety``
3. laws, plant  ``stagectl.control`` (pure control laws, trajectories) |
                ``stagectl.sim`` (stage plant and the virtual devices that speak the drivers' protocols)
4. offline      ``stagectl.ident`` (recordings, identify, discover), ``stagectl.plots``
5. runtime      ``stagectl.loop`` (the fixed-rate loop), ``stagectl.runtime``, ``stagectl.recorder``
6. config       ``stagectl.config``  -- YAML → typed, cross-checked configuration
7. assembly     ``stagectl.app``     -- configuration → devices, controller, safety, loop
8. service      ``stagectl.daemon``
9. benchmarks   ``stagectl.bench``
10. shell       ``stagectl.commands``, ``stagectl.cli``
"""

__version__ = "0.1.0"
