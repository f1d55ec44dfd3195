"""``python skewed_agent.py SKEW_S ARGS...``: ``fisc-agent ARGS`` on a companion clock ``SKEW_S`` seconds
off true time (negative: behind), as a companion computer without NTP or GNSS time would be.

The shift is applied to ``time.time``, the clock the agent reads UNIX time from (fleet-command
freshness, entry windows, its logs), before the agent is imported.  libfaketime, the system-wide way,
cannot be used with Python: it breaks timed waits (``time.sleep`` raised EINVAL, telemetry threads
never woke)."""

from __future__ import annotations

import sys
import time


def main() -> None:
    skew_s = float(sys.argv[1])
    real = time.time
    time.time = lambda: real() + skew_s
    from fisc_agent.cli import console

    sys.argv = ["fisc-agent", *sys.argv[2:]]
    console()


if __name__ == "__main__":
    main()
