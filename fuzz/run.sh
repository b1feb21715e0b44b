#!/usr/bin/env bash
# Runs every cargo-fuzz target of s3res for SECONDS each (default 30) and prints, per target,
# executions per second, coverage and the outcome. Exits non-zero if any target found a crash,
# a hang (an input running longer than 10 s) or an out-of-memory (above 2 GiB), or did not run.
#
#   fuzz/run.sh [--keep] [--minimize] [-j JOBS] [SECONDS [TARGET...]]
#
#   --keep   new inputs go into fuzz/corpus/TARGET (default: a scratch folder, so that a smoke
#            run leaves the checkout as it was; the committed corpus is read either way)
#   --minimize  afterwards, cut each corpus down to the inputs that cover its edges (a merge
#            with -use_counters=0: the same edges, few of the hit-count variants; what the
#            repository keeps)
#   -j JOBS  targets run at once (default 1; the machine has 2 cores)
#
# Needs a nightly toolchain (`cargo +nightly`) for the sanitizer flags; without one it uses the
# default toolchain with RUSTC_BOOTSTRAP=1. Installs cargo-fuzz if it is missing. Reproducers
# of anything found are in fuzz/artifacts/TARGET/; logs in fuzz/logs/TARGET.log. The inputs
# in fuzz/reproducers/TARGET/ (defects found before, and fixed) are replayed by every run.
set -uo pipefail
cd "$(dirname "$0")"

keep=0
minimize=0
jobs=1
while [ $# -gt 0 ]; do
    case "$1" in
        --keep) keep=1; shift ;;
        --minimize) minimize=1; shift ;;
        -j) jobs="$2"; shift 2 ;;
        -h|--help) sed -n '2,18p' "$0"; exit 0 ;;
        *) break ;;
    esac
done
seconds="${1:-30}"
shift || true

if rustup toolchain list 2>/dev/null | grep -q '^nightly'; then
    cargo=(cargo +nightly)
else
    echo "fuzz: no nightly toolchain; using the default one with RUSTC_BOOTSTRAP=1"
    export RUSTC_BOOTSTRAP=1
    cargo=(cargo)
fi

if ! "${cargo[@]}" fuzz --version >/dev/null 2>&1; then
    echo "fuzz: installing cargo-fuzz"
    cargo install cargo-fuzz --locked || exit 1
fi

if [ $# -gt 0 ]; then
    targets=("$@")
else
    mapfile -t targets < <("${cargo[@]}" fuzz list)
fi

echo "fuzz: building ${#targets[@]} targets (release, AddressSanitizer, debug assertions)"
"${cargo[@]}" fuzz build || exit 1

mkdir -p logs
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT

run_one() {
    local t="$1" new
    mkdir -p "corpus/$t"
    if [ "$keep" = 1 ]; then
        set -- "corpus/$t"
    else
        new="$scratch/$t"
        mkdir -p "$new"
        set -- "$new" "corpus/$t"
    fi
    # Inputs that once found a defect are replayed first, every run.
    if [ -d "reproducers/$t" ]; then
        set -- "$@" "reproducers/$t"
    fi
    # -timeout: an input that runs 10 s is a hang; -rss_limit_mb: 2 GiB is an out-of-memory.
    "${cargo[@]}" fuzz run "$t" "$@" -- \
        -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 -print_final_stats=1 \
        >"logs/$t.log" 2>&1
    echo $? >"logs/$t.status"
}

running=0
for t in "${targets[@]}"; do
    echo "fuzz: $t for ${seconds} s"
    run_one "$t" &
    running=$((running + 1))
    if [ "$running" -ge "$jobs" ]; then
        wait -n
        running=$((running - 1))
    fi
done
wait

failed=0
printf '\n%-20s %8s %10s %8s %8s %7s %8s  %s\n' target seconds runs "exec/s" cov ft corpus result
for t in "${targets[@]}"; do
    log="logs/$t.log"
    status=$(cat "logs/$t.status" 2>/dev/null || echo 1)
    runs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
    eps=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -1)
    took=$(sed -n 's/^Done [0-9]* runs in \([0-9]*\) second.*/\1/p' "$log" | tail -1)
    last=$(grep -E '^#[0-9]+.*cov: ' "$log" | tail -1)
    cov=$(sed -n 's/.*cov: \([0-9]*\).*/\1/p' <<<"$last")
    ft=$(sed -n 's/.* ft: \([0-9]*\).*/\1/p' <<<"$last")
    corp=$(sed -n 's/.* corp: \([0-9]*\).*/\1/p' <<<"$last")
    if [ "$status" = 0 ]; then
        result=ok
    else
        failed=1
        result="FAILED (exit $status): $(grep -m1 -E 'ERROR: libFuzzer|==ERROR|panicked at|deadly signal|timeout|out-of-memory' "$log" | cut -c1-120)"
    fi
    printf '%-20s %8s %10s %8s %8s %7s %8s  %s\n' "$t" "${took:--}" "${runs:--}" "${eps:--}" \
        "${cov:--}" "${ft:--}" "${corp:--}" "$result"
done
if [ "$minimize" = 1 ]; then
    echo
    for t in "${targets[@]}"; do
        min="$scratch/min-$t"
        mkdir -p "$min"
        "target/$(rustc -vV | sed -n 's/^host: //p')/release/$t" -merge=1 -use_counters=0 \
            "$min" "corpus/$t" >"logs/$t.min.log" 2>&1 || { failed=1; continue; }
        before=$(find "corpus/$t" -type f | wc -l)
        rm -rf "corpus/$t" && mv "$min" "corpus/$t"
        echo "fuzz: corpus/$t minimized: $before -> $(find "corpus/$t" -type f | wc -l) inputs," \
            "$(cat "corpus/$t"/* | wc -c) bytes, $(sed -n 's/.* \([0-9]*\) new coverage edges.*/\1/p' "logs/$t.min.log") edges"
    done
fi
if [ "$failed" != 0 ]; then
    echo
    echo "fuzz: a target failed; its log is in fuzz/logs/, its reproducer in fuzz/artifacts/"
    for t in "${targets[@]}"; do
        if [ "$(cat "logs/$t.status" 2>/dev/null || echo 1)" != 0 ]; then
            echo "== $t"
            tail -40 "logs/$t.log"
        fi
    done
fi
exit "$failed"
