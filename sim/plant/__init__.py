"""The paper's quadrotor velocity plant: the vectorised model, its parameters, the step kernel
(numpy reference and numba), the scalar oracle, plants fitted to flight logs, and the paper's plant checks.
"""
