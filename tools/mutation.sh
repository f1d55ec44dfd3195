#!/usr/bin/env bash
# Mutation testing of the safety predicates and metrics (issue 38, docs/testing.md).
#
#   tools/mutation.sh                 # every module in the table below, one after the other
#   tools/mutation.sh position_gate   # one or more modules by key
#   tools/mutation.sh --list          # the table
#
# A row may name, in a fourth column, the functions to mutate (mutmut mutant-name globs such as
# 'fisc_agent.flight.mission.x_gate_*'); the other functions of the module are then neither mutated
# nor counted.
#
# Each module is mutated by mutmut (pip install 'fisc[mutation]', part of the test extra) and judged by ITS OWN focused unit tests only
# (never the whole suite, never SITL), one module at a time, one worker (--max-children 1).  The checkout is
# copied to a scratch directory per module ($FISC_MUTATION_DIR, default ${TMPDIR:-/tmp}/fisc-mutation), so the
# working tree is never touched; each run starts afresh (a changed test re-judges every mutant).
#
# The summary prints, per module, killed / non-equivalent mutants: a surviving mutant listed in
# tools/mutation_equivalent.txt (with the reason it cannot change behaviour) counts as equivalent and is left
# out of the ratio; every other survivor is printed and counts against the module.  Exit status 1 when a
# module is below the target (90 %), 2 on a usage error.
set -euo pipefail

REPO="$(cd "$(dirname "$0")/.." && pwd)"
PY="${PYTHON:-python3}"
[ -x "$REPO/.venv/bin/python" ] && [ -z "${PYTHON:-}" ] && PY="$REPO/.venv/bin/python"
MUTMUT=("$PY" -m mutmut)
WORK="${FISC_MUTATION_DIR:-${TMPDIR:-/tmp}/fisc-mutation}"
EQUIV="$REPO/tools/mutation_equivalent.txt"
TARGET_PCT=90

# key | the module mutated | its focused tests (space separated) [| only these functions (mutant-name globs)]
TABLE="
position_gate  | fisc_agent/flight/position_gate.py | tests/hostile/test_inputs_pure.py
command_gate   | fisc_agent/zenoh/command_gate.py   | tests/zenoh/test_fleet_commands_v2.py
fleet_commands | fisc_agent/zenoh/fleet_commands.py | tests/zenoh/test_fleet_commands_v2.py
frames         | fisc_agent/flight/frames.py        | tests/fisc_agent/test_agent_frames.py tests/sim/autopilot/test_autopilot_geodesy.py
failsafe       | fisc_agent/flight/failsafe.py      | tests/fisc_agent/test_agent_failsafe.py
authority      | fisc_agent/flight/authority.py     | tests/fisc_agent/test_authority.py
chunks         | fisc_agent/map/chunks.py           | tests/hostile/test_inputs_pure.py tests/zenoh/test_codecs.py
metrics        | fisc_ground/fields/metrics.py      | tests/fisc_ground/test_metrics.py
swarm_fields   | fisc_ground/fields/swarm_fields.py | tests/fisc_ground/test_swarm_fields.py
codec          | fisc_agent/map/codec.py            | tests/fisc_agent/test_mapfile.py tests/fisc_agent/test_map_codec.py
health         | fisc_agent/flight/health.py        | tests/fisc_agent/test_vehicle_health.py
readiness      | fisc_agent/flight/readiness.py     | tests/fisc_agent/test_authority.py tests/fisc_agent/test_vehicle_health.py
mission        | fisc_agent/flight/mission.py       | tests/fisc_agent/test_agent_mission.py tests/fisc_agent/test_authority.py tests/fisc_agent/test_mission_reasons.py
safety_net     | fisc_agent/flight/safety_net.py     | tests/fisc_agent/test_safety_net.py
cross_stream   | fisc_agent/flight/tracking.py       | tests/fisc_agent/test_tracking.py | fisc_agent.flight.tracking.x_cross_stream*
"

field() { echo "$1" | cut -d'|' -f"$2" -s | xargs; }
row_of() { echo "$TABLE" | grep -E "^$1 +\|" || true; }

if [ "${1:-}" = "--list" ]; then echo "$TABLE" | sed '/^$/d'; exit 0; fi
if [ $# -eq 0 ]; then
  set -- $(echo "$TABLE" | sed '/^$/d' | cut -d'|' -f1)
fi
for key in "$@"; do
  [ -n "$(row_of "$key")" ] || { echo "tools/mutation.sh: unknown module '$key' (see --list)" >&2; exit 2; }
done
"$PY" -c "import mutmut" 2>/dev/null || {
  echo "tools/mutation.sh: mutmut is not installed for $PY (pip install -e '.[mutation]', part of '.[test]')" >&2; exit 2; }

equivalent_of() {  # the mutant names listed as equivalent (first word of each non-comment line)
  [ -f "$EQUIV" ] && sed -e 's/#.*//' "$EQUIV" | awk 'NF {print $1}' || true
}

run_one() {
  local key="$1" row src tests only dir
  row="$(row_of "$key")"
  src="$(field "$row" 2)"
  tests="$(field "$row" 3)"
  only="$(field "$row" 4)"
  dir="$WORK/$key"
  rm -rf "$dir" && mkdir -p "$dir"
  # the checkout as it is: tracked and new files, without what .gitignore ignores
  (cd "$REPO" && git ls-files -co --exclude-standard -z | tar --null --ignore-failed-read -T - -cf - 2>/dev/null) \
    | tar -xf - -C "$dir"
  {
    echo "[mutmut]"
    echo "source_paths ="; printf '    %s\n' fisc_agent fisc_ground sim field_maps
    echo "only_mutate ="; printf '    %s\n' "$src"
    echo "pytest_add_cli_args_test_selection ="; printf '    %s\n' $tests
    echo "pytest_add_cli_args ="; printf '    %s\n' -p no:cacheprovider -p no:randomly
  } > "$dir/setup.cfg"
  echo "== $key: mutating $src${only:+ ($only)} against $tests"
  # shellcheck disable=SC2086  # the globs are words for mutmut, not for the shell
  (cd "$dir" && set -f && "${MUTMUT[@]}" run --max-children 1 $only > "$dir/run.log" 2>&1) || {
    echo "   mutmut failed; the last lines of $dir/run.log:"; tail -c 2000 "$dir/run.log" | tr '\r' '\n' | tail -15
    return 1; }
  (cd "$dir" && "${MUTMUT[@]}" results --all true 2>/dev/null) | sed 's/^ *//' | in_scope "$only" > "$dir/results.txt"
}

in_scope() {  # the result lines of the mutants the row's globs select (every line without globs)
  local globs="$1" line name g
  set -f
  while IFS= read -r line; do
    name="${line%%:*}"
    if [ -z "$globs" ]; then echo "$line"; continue; fi
    for g in $globs; do
      # shellcheck disable=SC2053  # $g is a glob on purpose
      if [[ $name == $g ]]; then echo "$line"; break; fi
    done
  done
  set +f
}

summarise() {
  local key="$1" dir="$WORK/$1" total killed surv equiv nonequiv pct
  local eq; eq="$(equivalent_of)"
  total=$(grep -c ': ' "$dir/results.txt" || true)
  killed=$(grep -c -E ': (killed|timeout|caught by type check)$' "$dir/results.txt" || true)
  equiv=0; surv=()
  while IFS= read -r line; do
    name="${line%%:*}"
    if grep -qxF "$name" <<<"$eq"; then equiv=$((equiv + 1)); else surv+=("$line"); fi
  done < <(grep -v -E ': (killed|timeout|caught by type check)$' "$dir/results.txt" || true)
  nonequiv=$((total - equiv))
  if [ "$nonequiv" -gt 0 ]; then pct=$((100 * killed / nonequiv)); else pct=100; fi
  printf '%-15s %4d killed / %4d non-equivalent  (%3d %%; %d equivalent, %d mutants)\n' \
    "$key" "$killed" "$nonequiv" "$pct" "$equiv" "$total"
  for s in "${surv[@]+"${surv[@]}"}"; do echo "    $s"; done
  [ "$pct" -ge "$TARGET_PCT" ]
}

failed=0
for key in "$@"; do run_one "$key" || failed=1; done
echo
echo "mutation kill ratio, $(date -u +%Y-%m-%d) (target >= $TARGET_PCT % per module):"
for key in "$@"; do
  if [ -f "$WORK/$key/results.txt" ]; then summarise "$key" || failed=1
  else echo "$key: no results"; failed=1; fi
done
echo "(survivors: 'cd $WORK/<key> && $PY -m mutmut show <name>' prints the mutant's diff)"
exit "$failed"
