#!/usr/bin/env bash
# The default method's `reloc eval` of the sets every answer-changing change is checked on
# (dev presets, validation presets, real sets with their keyframes' pose uncertainty), one set
# at a time, niced; then `python3 scripts/compare_eval.py BEFORE_DIR OUTDIR` compares per query.
#   usage: scripts/eval_sets.sh OUTDIR [SET...]      (default: all 18)
#   DEV, VAL, REAL: where the dev presets, the validation presets (NAME_s1, ...) and the real
#   sets are; RELOC: the reloc command; FOCAL: a focal scale the queries claim
#   (`--query-focal-scale`, a stale or wrong CameraInfo), e.g. FOCAL=1.15; OPTIONS: a TOML
#   file of plugin options (`--options`), e.g. one setting `[multi] duplicates_early = true`.
set -u
OUT=$1; shift; mkdir -p "$OUT"
DEV=${DEV:-/work/data}; VAL=${VAL:-/work/data/val}; REAL=${REAL:-/work/shared/data/real}
RELOC=${RELOC:-.venv/bin/reloc}
SCALE=${FOCAL:+--query-focal-scale $FOCAL}
OPTS=${OPTIONS:+--options $OPTIONS}
declare -A ARGS=(
  [tum]="$REAL/tum_fr1_rpy --keyframe-sigma 0.01,0.3"
  [7scenes]="$REAL/7scenes_redkitchen --keyframe-sigma 0.015,0.45"
  [fountain]="$REAL/strecha_fountain_p11 --keyframe-sigma 0.002,0.01"
  [herzjesu]="$REAL/strecha_herzjesu_p25 --keyframe-sigma 0.002,0.01")
for p in desk desk-hard room room-hard repeated repeated-hard; do ARGS[$p]=$DEV/$p; done
for d in "$VAL"/*; do [ -d "$d" ] && ARGS[$(basename "$d")]=$d; done
SETS=${*:-tum 7scenes fountain herzjesu desk desk-hard room room-hard repeated repeated-hard
  desk_s1 desk-hard_s1 room_s1 room-hard_s1 repeated_s1 repeated-hard_s1 repeated_s2 repeated-hard_s2}
for n in $SETS; do
  if [ -z "${ARGS[$n]:-}" ]; then echo "$n: unknown set (expected one of: ${!ARGS[*]})"; exit 2; fi
  # shellcheck disable=SC2086  # the set's arguments are words
  nice -n 15 $RELOC eval ${ARGS[$n]} -m default $SCALE $OPTS --json "$OUT/$n.json" --no-progress \
    > "$OUT/$n.log" 2>&1
  echo "$n rc=$? $(date +%T)"
done
