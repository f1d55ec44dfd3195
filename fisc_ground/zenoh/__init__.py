"""Zenoh on the ground: sessions and lab discovery (config), the map server (publish), fleet
commands and status (fleet), the router, and the Zenoh subcommands (cli).
"""
