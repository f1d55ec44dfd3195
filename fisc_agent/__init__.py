"""FISC onboard agent: map reading, CV lookup, MAVLink link and failsafes (numpy + stdlib only)."""
