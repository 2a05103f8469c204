"""The Python side of rfcl's simulator workers (ManiSkill3, MetaWorld, Adroit).

The Rust actor drives these adapters; `python -m rfcl_sim.check` verifies the tested package matrix.
"""
