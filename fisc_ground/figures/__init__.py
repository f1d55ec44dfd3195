"""Figures: the paper's map and field plots, a run's figure set, rendered on two processes.
"""
