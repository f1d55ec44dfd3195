"""From a reference field to fitted CVs (pure numerics): the cubic partition, the designed
staircase, the paper's velocity fitting, the pressure and speed scaling, the staggered field.
"""
