"""Shipped reference flow data and ready maps (the embedded default)."""
