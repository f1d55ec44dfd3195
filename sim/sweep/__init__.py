"""``fisc-sim sweep``: a spec's grid of runs (spec), run on dask (run), and its CLI (cli).
"""
