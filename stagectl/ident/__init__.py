"""Offline analysis: recordings I/O, friction identification and the discovery workflow.

Modules, each importing only those before it (no cycles)::

    recording -> signals -> columns, search, localise -> hypothesis -> effects (the EffectSpec REGISTRY)
              -> regress -> modelio -> results -> discover -> report;   identify, synth (tests and demos)

To add a discovery effect, see :mod:`stagectl.ident.effects`.
"""
