"""Every file argument refuses a non-regular, huge or sparse file at once (issue 12, finding 6).

Each case runs the real console script as a child process and watches it: the child is
SIGKILLed if its resident memory passes ``KILL_RSS_MB`` (so a regression that reads
``/dev/zero`` until memory runs out fails here in a fraction of a second instead of taking the
machine down), and its exact peak RSS comes from ``wait4``.  The wall time is printed (``-s``)
for the record; speed targets live in benchmarks, so the test bounds it only by a generous
hang guard.
"""

from __future__ import annotations

import subprocess
import threading
import time
from pathlib import Path

import pytest

from fisc_agent.map.codec import encode_map
from fisc_ground.maps.write import generate_keypair

from .conftest import child_env, cli, free_tcp_port, free_udp_port, write_zenoh_config

MAX_RSS_MB = 200
KILL_RSS_MB = 400
HANG_GUARD_S = 30.0


def _status_kb(status: Path, field: str) -> int | None:
    try:
        for line in status.read_text().splitlines():
            if line.startswith(field):
                return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return None


def run_watched(argv: list, timeout_s: float = HANG_GUARD_S) -> tuple[int, float, float, str]:
    """(exit code, wall seconds, peak RSS MB, stdout+stderr) of a child, killed beyond KILL_RSS_MB.

    The peak is the child's own ``VmHWM`` (high-water mark of its address space after exec),
    sampled every 5 ms until it exits.  ``wait4``'s ``ru_maxrss`` would be wrong here: it also
    counts the pages of the forked test process before the exec (200+ MB in a full run)."""
    t0 = time.monotonic()
    proc = subprocess.Popen([str(a) for a in argv], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, env=child_env())
    notes: list[str] = []
    peak_kb = [0]
    tail = [str(a).encode() for a in argv[1:]]

    def execed(cmdline: Path) -> bool:
        """True once the child runs our command (before its exec it is a copy of this process)."""
        try:
            parts = cmdline.read_bytes().rstrip(b"\0").split(b"\0")
        except OSError:
            return False
        return parts[-len(tail):] == tail

    def watchdog() -> None:
        status = Path(f"/proc/{proc.pid}/status")
        while proc.poll() is None:
            hwm = _status_kb(status, "VmHWM:")
            if hwm is not None and execed(status.parent / "cmdline"):
                peak_kb[0] = max(peak_kb[0], hwm)
            rss = _status_kb(status, "VmRSS:")
            if rss is not None and rss > KILL_RSS_MB * 1024:
                notes.append(f" [killed at {rss / 1024:.0f} MB]")
                proc.kill()
                return
            if time.monotonic() - t0 > timeout_s:
                notes.append(f" [killed after {timeout_s} s]")
                proc.kill()
                return
            time.sleep(0.005)

    guard = threading.Thread(target=watchdog, daemon=True)
    guard.start()
    out = proc.stdout.read().decode(errors="replace")
    proc.wait()
    wall = time.monotonic() - t0
    guard.join(1.0)
    return proc.returncode, wall, peak_kb[0] / 1024, out + "".join(notes)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("files")
    from tests.zenoh.conftest import map_parts

    key, pub = generate_keypair(d / "ground")
    from fisc_ground.maps.write import read_signing_key

    good = d / "good.fiscmap"
    good.write_bytes(encode_map(*map_parts(1), read_signing_key(key)))
    port = free_tcp_port()
    cfg = write_zenoh_config(d / "z.json5", [f"tcp/127.0.0.1:{port}"], [])
    return {"good": good, "pub": pub, "key": key, "cfg": cfg, "dir": d}


def _cases(f: dict) -> dict[str, list]:
    z = ["--zenoh-config", f["cfg"]]
    udp = f"udpin:127.0.0.1:{free_udp_port()}"
    return {
        "inspect MAP": [*cli("fisc-ground"), "inspect", "/dev/zero"],
        "inspect --trusted-key": [*cli("fisc-ground"), "inspect", f["good"], "--trusted-key", "/dev/zero"],
        "plot --trusted-key": [*cli("fisc-ground"), "plot", f["good"], "--trusted-key", "/dev/zero", "-o", f["dir"] / "p"],
        "publish MAP": [*cli("fisc-ground"), "publish", "/dev/zero", "--swarm", "t", "--duration", "1", *z],
        "replay FILE": [*cli("fisc-ground"), "replay", "/dev/zero", "-o", f["dir"] / "r"],
        "replay --map": [*cli("fisc-ground"), "replay", f["dir"] / "missing.rec", "--map", "/dev/zero", "-o", f["dir"] / "r2"],
        "monitor --map": [*cli("fisc-ground"), "monitor", "--swarm", "t", "--map", "/dev/zero", "--duration", "1", *z],
        "monitor --trusted-key": [*cli("fisc-ground"), "monitor", "--swarm", "t", "--trusted-key", "/dev/zero",
                                  "--duration", "1", *z],
        "cmd --key": [*cli("fisc-ground"), "cmd", "hold", "--swarm", "t", "--key", "/dev/zero", "--wait", "0.1", *z],
        "fit --sign": [*cli("fisc-ground"), "fit", "analytic", "-o", f["dir"] / "x.fiscmap", "--sign", "/dev/zero"],
        "fit REFERENCE": [*cli("fisc-ground"), "fit", "/dev/zero", "-o", f["dir"] / "y.fiscmap"],
        "fisc-sim run --map": [*cli("fisc-sim"), "run", "--map", "/dev/zero", "-o", f["dir"] / "run"],
        "fisc-sim emulate --map": [*cli("fisc-sim"), "emulate", "--map", "/dev/zero", "--agents", "2", "-q",
                                   "-o", f["dir"] / "emu"],
        "fisc-agent --map": [*cli("fisc-agent"), "--map", "/dev/zero", "--mavlink", udp, "--id", "1"],
        "fisc-agent --trusted-key": [*cli("fisc-agent"), "--map", f["good"], "--trusted-key", "/dev/zero",
                                     "--mavlink", udp, "--id", "1"],
    }


CASES = ["inspect MAP", "inspect --trusted-key", "plot --trusted-key", "publish MAP", "replay FILE", "replay --map",
         "monitor --map", "monitor --trusted-key", "cmd --key", "fit --sign", "fit REFERENCE", "fisc-sim run --map",
         "fisc-sim emulate --map",
         "fisc-agent --map",
         "fisc-agent --trusted-key"]


@pytest.mark.parametrize("case", CASES)
def test_dev_zero_is_refused_at_once(files, case):
    argv = _cases(files)[case]
    rc, wall, rss_mb, out = run_watched(argv)
    print(f"\n/dev/zero {case}: exit {rc}, {wall:.2f} s, peak RSS {rss_mb:.0f} MB")
    assert rc in (1, 2), f"{case}: exit {rc}\n{out}"
    assert "must be a regular file, this is a character device" in out, out
    assert rss_mb < MAX_RSS_MB, f"{case}: peak RSS {rss_mb:.0f} MB"


def test_fit_refuses_a_sparse_2gb_csv_and_vtu_at_once(tmp_path):
    """`fit` on a 2 GB sparse CSV took 96 s and 6.4 GB and then said "header only"; on a sparse
    VTU it gave a ReadError with an empty message."""
    csv = tmp_path / "huge.csv"
    with open(csv, "wb") as fh:
        fh.write(b"x,y,z,x-velocity,y-velocity,z-velocity,pressure\n")
        fh.truncate(2 * 10**9)
    vtu = tmp_path / "huge.vtu"
    with open(vtu, "wb") as fh:
        fh.truncate(2 * 10**9)
    for path in (csv, vtu):
        rc, wall, rss_mb, out = run_watched([*cli("fisc-ground"), "fit", path, "-o", tmp_path / "m.fiscmap"])
        print(f"\nfit on a sparse 2 GB {path.suffix}: exit {rc}, {wall:.2f} s, peak RSS {rss_mb:.0f} MB")
        assert rc == 2, out  # invalid input (fisc_agent.common.cli_common)
        assert str(path) in out and ("sparse" in out or "NUL byte" in out), out
        assert "ReadError: \n" not in out and "header only" not in out
        assert rss_mb < MAX_RSS_MB


def test_a_zero_filled_csv_that_is_not_sparse_is_refused_by_its_head(tmp_path):
    path = tmp_path / "zeros.csv"
    path.write_bytes(b"\0" * (1 << 20))
    rc, _, _, out = run_watched([*cli("fisc-ground"), "fit", path, "-o", tmp_path / "m.fiscmap"])
    assert rc == 2 and "NUL byte at offset 0" in out, out


def test_inspect_checks_size_and_magic_before_reading_a_2gb_file(tmp_path):
    """`inspect` read a 2 GB file whole before checking the 8-byte magic."""
    big, wrong = tmp_path / "big.fiscmap", tmp_path / "wrong.fiscmap"
    with open(big, "wb") as fh:
        fh.write(b"FISCMAP\0")
        fh.truncate(2 * 10**9)
    with open(wrong, "wb") as fh:
        fh.write(b"NOTAMAP!")
        fh.truncate(900 * 2**20)  # under the 1 GiB cap: refused on its first 8 bytes
    for path, expect in ((big, "size: FISC map is 1.86 GiB, larger than the 1 GiB limit"), (wrong, "magic: not a FISC map")):
        rc, wall, rss_mb, out = run_watched([*cli("fisc-ground"), "inspect", path])
        print(f"\ninspect {path.name}: exit {rc}, {wall:.2f} s, peak RSS {rss_mb:.0f} MB")
        assert rc == 2 and expect in out, out
        assert rss_mb < MAX_RSS_MB
