"""The Python side of rfcl: the simulator workers' adapters (ManiSkill3, MetaWorld, Adroit, your
own Gymnasium envs), demo files and demo sources, and a NumPy loader for exported policies.

* :func:`load_policy` (:mod:`rfcl_sim.policy`): a run's policy as a NumPy callable;
* :mod:`rfcl_sim.demo_file`: read and write rfcl's demo files;
* :mod:`rfcl_sim.adapters`: the adapter contract and the suites;
* ``python -m rfcl_sim.demos``: demo sources; ``python -m rfcl_sim.check``: the tested package
  matrix.
"""
from .policy import Policy, PolicyError, load_policy

__all__ = ["Policy", "PolicyError", "load_policy"]
