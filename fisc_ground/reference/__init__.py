"""Reference flow-field importers (Fluent CSV, VTK/VTU, axisymmetric CSV) and the analytic reference."""
