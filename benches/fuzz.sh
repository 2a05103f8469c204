#!/usr/bin/env bash
# Fuzzing benchmark job (NOT part of CI): builds every cargo-fuzz target of fuzz/ on the stable
# toolchain and runs each for SECONDS of wall time (default 120) with one libFuzzer worker, then
# prints per target the CPU seconds, executions, exec/s, corpus size and new crash reproducers.
# See docs/FUZZING.md.
#
#   benches/fuzz.sh [SECONDS] [TARGET...]
#
# Environment: SANITIZER (default address; `none` builds without ASan), CARGO_BUILD_JOBS
# (default 1), FUZZ_LOG_DIR (default fuzz/target/fuzz-logs). New inputs are added to
# fuzz/corpus/<target>/ and crash reproducers to fuzz/artifacts/<target>/: minimize the corpus
# afterwards (`cargo fuzz cmin <target>`) before committing it.
set -uo pipefail

seconds=${1:-120}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    targets=(rpc_decode demo_hdf5 config_overrides shm_frame)
fi

cd "$(dirname "$0")/../fuzz" || exit 1
export RUSTC_BOOTSTRAP=1 # libfuzzer-sys and -Zsanitizer need nightly flags; stable rustc allows them with this
export CARGO_BUILD_JOBS=${CARGO_BUILD_JOBS:-1}
sanitizer=${SANITIZER:-address}
logs=${FUZZ_LOG_DIR:-$PWD/target/fuzz-logs}
mkdir -p "$logs"

echo "building ${targets[*]} (sanitizer $sanitizer) ..."
for t in "${targets[@]}"; do
    cargo fuzz build -s "$sanitizer" "$t" || { echo "build of $t failed" >&2; exit 1; }
done

count() { find "$1" -maxdepth 1 -type f 2>/dev/null | wc -l; }

rows=()
failed=0
for t in "${targets[@]}"; do
    mkdir -p "artifacts/$t" "corpus/$t"
    before=$(count "artifacts/$t")
    log="$logs/$t.log"
    # The HDF5 C library (1.10, Debian's libhdf5_serial) leaks a few KiB on some corrupt files
    # and asks malloc for sizes read from the file, handling the NULL it gets back
    # (fuzz/artifacts/demo_hdf5/, docs/FUZZING.md): for that target LeakSanitizer is off and
    # ASan's malloc returns NULL, as glibc's does, instead of aborting.
    extra=()
    asan=${ASAN_OPTIONS:-}
    if [ "$t" = demo_hdf5 ]; then
        extra=(-detect_leaks=0)
        asan="${asan:+$asan:}allocator_may_return_null=1:detect_leaks=0"
    fi
    echo "fuzzing $t for ${seconds}s (log: $log) ..."
    TIMEFORMAT='%U %S'
    cpu=$( { time ASAN_OPTIONS="$asan" cargo fuzz run -s "$sanitizer" "$t" -- -max_total_time="$seconds" \
        -print_final_stats=1 "${extra[@]}" >"$log" 2>&1; } 2>&1 )
    cpu=$(awk '{printf "%.0f", $1 + $2}' <<<"$cpu")
    execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
    rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -1)
    files=$(count "corpus/$t")
    bytes=$(du -sk "corpus/$t" | cut -f1)
    new=$(( $(count "artifacts/$t") - before ))
    if [ "$new" -gt 0 ]; then
        failed=1
        finding="$new NEW: $(ls -t "artifacts/$t" | head -"$new" | tr '\n' ' ')"
    else
        finding="none"
    fi
    rows+=("$(printf '| %s | %s | %s | %s | %s files, %s KiB | %s |' \
        "$t" "$cpu" "${execs:-?}" "${rate:-?}" "$files" "$bytes" "$finding")")
done

echo
echo "| target | CPU s | executions | exec/s | corpus | crashes |"
echo "|---|---|---|---|---|---|"
printf '%s\n' "${rows[@]}"
exit $failed
