"""The command map onboard: its file format (codec), transport chunks, the CV lookup and every
command mode (lookup), the kinetic deviation, the duct wall and the slot hash.

Interface: ``codec.load_map`` / ``decode_map`` -> ``CommandMap``; ``lookup.CommandField`` (vectorised)
and ``lookup.flight_command``; ``chunks.MapAssembler`` for maps arriving in pieces.
"""
