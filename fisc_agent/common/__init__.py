"""Conventions every FISC command shares (stdlib only): CLI options and exit codes, the bounded
reader of file arguments, the swarm-name rule and rate-limited logging.
"""
