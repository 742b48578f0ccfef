"""Hyperparameter sweeps: a YAML spec → trials × seeds, trained and tested, ranked by an objective.

A spec (:class:`~safelane.running.sweeps.spec.SweepSpec`, examples in ``configs/sweeps/``) names one method, a
search space over any ``--set`` key (``agent.*``, ``reward.*``, ``shield.*``, ``env.*`` …), how to search it
(``grid``: every combination; ``random``: ``samples`` points drawn from ``search_seed``; ``tpe``: ``samples``
trials proposed by Optuna's TPE sampler from the results so far, in batches of ``batch``, see
:mod:`safelane.running.sweeps.tpe`), the seeds of every point, the training length and test episodes, and the
objective: a test metric to maximise or minimise, subject to constraints such as ``collision_rate <= 0.01``.

:func:`~safelane.running.sweeps.sweep.run_sweep` turns the spec into *trials* (a point of the space,
``DIR/trials/tNNN/``), each trained and tested once per seed by the experiment runner's task
(``DIR/trials/tNNN/runs/METHOD-sS``), on either backend of :mod:`safelane.running.backend`. What it writes, always
rebuilt from the trial directories (so a killed sweep, re-run, neither repeats nor loses nor doubles a row):

* ``trials.csv``: one row per trial and seed — parameters, seed, status (``ok`` / ``failed``), metrics,
  the error of a failed one;
* ``summary.md`` / ``summary.json``: per trial the objective's mean over seeds with a bootstrap 95 %
  interval, the pooled collision rate with its Wilson interval, whether the constraints hold; the best
  feasible trial;
* ``best.yaml``: the agent preset of the best trial (the spec's agent preset with the trial's
  ``agent.*`` values), ready for ``--agent-preset DIR/best.yaml``; its other keys as ``--set`` lines in
  a comment;
* ``objective_PARAM.png``: the objective against each parameter (mean and interval per trial).
"""

from safelane.running.sweeps.spec import SweepSpec, load_sweep_spec
from safelane.running.sweeps.sweep import run_sweep

__all__ = ["SweepSpec", "load_sweep_spec", "run_sweep"]
