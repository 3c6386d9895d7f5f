"""Commissioning: from an unknown stage to a tuned, friction-compensated controller (``stagectl commission``).

Modules (see ``docs/commissioning.md`` for the experiments and the decision rules):

* :mod:`~stagectl.commission.envelope` -- the limits every experiment stays inside and the amplitudes derived
  from them (soft limits, force, velocity, command-line lowering);
* :mod:`~stagectl.commission.controllers` -- what the loop runs during an experiment: the open-loop sanity
  probe and the closed-loop wrapper adding a known force excitation;
* :mod:`~stagectl.commission.analysis` -- FRF estimation and fit, sanity evaluation, constant-velocity friction
  regression, margins on the measured FRF;
* :mod:`~stagectl.commission.sequence` -- the experiment sequence on a built stage;
* :mod:`~stagectl.commission.outputs` -- model.yaml, stage.yaml, report.md/json and plots;
* :mod:`~stagectl.commission.guard` -- refusal while the daemon holds the same devices.
"""
