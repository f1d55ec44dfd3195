"""Swarm fields and how faithful they are: the paper's quartet per CV from agent samples
(swarm_fields, swarm_equations), the fidelity metrics, one run's fields (field_run, field_report) and
one flown pass scored against the CFD (flight_score).
"""
