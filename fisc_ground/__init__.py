"""FISC ground tools: reference fields, control volumes, velocity fitting, command maps, swarm fields."""
