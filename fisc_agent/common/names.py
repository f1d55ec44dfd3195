"""The one rule for swarm names and key-expression prefixes, shared by every command.

``fisc-agent --swarm/--zenoh-prefix``, ``fisc-sim emulate --swarm/--zenoh-prefix`` and
``fisc-ground publish|cmd|status|monitor --swarm/--prefix`` all parse their values with
``swarm_name_arg`` / ``prefix_arg``, so a name that one command accepts every other command
accepts too (a fleet that can be given a map can also be held), and a bad value ends in a
usage error (exit 2) naming the rule instead of a Zenoh error at the first publication.

* A **swarm name** is one key-expression chunk of 1..``MAX_SWARM_NAME_BYTES`` characters from
  ``A-Z a-z 0-9 _ - .`` (so it fits the fleet-command wire format's one-byte length, and contains
  no wildcard, ``/``, ``@`` verbatim marker, space or control character).
* A **prefix** is 1..``MAX_PREFIX_CHUNKS`` such chunks joined by ``/`` (no leading, trailing or
  doubled ``/``), at most ``MAX_PREFIX_BYTES`` in all.

Standard library only (onboard code).
"""

from __future__ import annotations

import argparse
import re

MAX_SWARM_NAME_BYTES = 64
MAX_PREFIX_BYTES = 128
MAX_PREFIX_CHUNKS = 8
_CHUNK = re.compile(r"[A-Za-z0-9_.\-]+")


class KeyNameError(ValueError):
    """A swarm name or prefix breaks the rule (the message states the rule)."""


def check_swarm_name(name: str) -> str:
    """``name`` if it is a valid swarm name, else ``KeyNameError`` stating the rule."""
    if not isinstance(name, str) or not name:
        raise KeyNameError("swarm name is empty")
    if len(name) > MAX_SWARM_NAME_BYTES:
        raise KeyNameError(f"swarm name is {len(name.encode())} bytes long; at most {MAX_SWARM_NAME_BYTES} allowed")
    if not _CHUNK.fullmatch(name) or name in (".", ".."):
        raise KeyNameError(f"swarm name {name!r} may only contain A-Z a-z 0-9 _ - . (one key-expression chunk)")
    return name


def check_prefix(prefix: str) -> str:
    """``prefix`` if it is a valid key-expression prefix, else ``KeyNameError`` stating the rule."""
    if not isinstance(prefix, str) or not prefix:
        raise KeyNameError("prefix is empty")
    if len(prefix) > MAX_PREFIX_BYTES:
        raise KeyNameError(f"prefix is {len(prefix.encode())} bytes long; at most {MAX_PREFIX_BYTES} allowed")
    chunks = prefix.split("/")
    if len(chunks) > MAX_PREFIX_CHUNKS:
        raise KeyNameError(f"prefix {prefix!r} has {len(chunks)} chunks; at most {MAX_PREFIX_CHUNKS} allowed")
    for chunk in chunks:
        if not chunk:
            raise KeyNameError(f"prefix {prefix!r} has an empty chunk (leading, trailing or doubled '/')")
        if not _CHUNK.fullmatch(chunk) or chunk in (".", ".."):
            raise KeyNameError(f"prefix {prefix!r}: chunk {chunk!r} may only contain A-Z a-z 0-9 _ - . "
                             "(chunks separated by '/')")
    return prefix


def swarm_name_arg(text: str) -> str:
    """argparse ``type=`` for ``--swarm`` (a bad name is a usage error, exit 2)."""
    try:
        return check_swarm_name(text)
    except KeyNameError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def prefix_arg(text: str) -> str:
    """argparse ``type=`` for ``--prefix`` / ``--zenoh-prefix`` (a bad prefix is a usage error, exit 2)."""
    try:
        return check_prefix(text)
    except KeyNameError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
