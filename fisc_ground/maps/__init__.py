"""Command maps from the ground: build a map from a reference (build), write and sign it
atomically (write), the duct wall it carries (duct_wall).  The format itself is
``fisc_agent.map.codec``.
"""
