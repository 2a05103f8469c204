# What the bench scripts share; `source benches/lib.sh` from the repository root.

# parse_flags SCRIPT NAME... -- ARGS...: each `--some-name VALUE` in ARGS sets the variable
# some_name, which must be one of the NAMEs (the script sets their defaults before); -h/--help
# prints the script's leading comment. Anything else stops the script with a line naming it.
parse_flags() {
    local script=$1 known=" " name
    shift
    while [[ $# -gt 0 && $1 != -- ]]; do known+="$1 "; shift; done
    [[ $# -gt 0 ]] && shift
    while [[ $# -gt 0 ]]; do
        case $1 in
            -h|--help) awk 'NR > 1 && !/^#/ {exit} NR > 1 {print}' "$script"; exit 0 ;;
            --*)
                name=${1#--}
                name=${name//-/_}
                if [[ $known != *" $name "* ]]; then
                    echo "$(basename "$script"): unknown argument $1 (see --help)" >&2; exit 2
                fi
                if [[ $# -lt 2 ]]; then
                    echo "$(basename "$script"): $1 needs a value (see --help)" >&2; exit 2
                fi
                printf -v "$name" '%s' "$2"
                shift 2 ;;
            *) echo "$(basename "$script"): unknown argument $1 (see --help)" >&2; exit 2 ;;
        esac
    done
}

# need_rfcl SCRIPT: the release build of rfcl, or a line saying how to build it.
need_rfcl() {
    rfcl=target/release/rfcl
    [[ -x $rfcl ]] || { echo "$(basename "$1"): $rfcl is not built (cargo build --release)" >&2; exit 1; }
}

# demos_or_generate ENV FILE: generates 5 demos of ENV into FILE unless it exists.
demos_or_generate() {
    if [[ ! -f $2 ]]; then
        mkdir -p "$(dirname "$2")"
        "$rfcl" demos generate --env "$1" -n 5 --out "$2"
    fi
}

# train_once WHAT DIR ARGS...: `rfcl train --run-dir DIR ARGS...`, its output in DIR.log, announced
# on stderr as WHAT. A DIR with a summary.json is kept, so that rerunning a script resumes its
# table; a failed run is reported and the script goes on to the next.
train_once() {
    local what=$1 dir=$2
    shift 2
    if [[ -f $dir/summary.json ]]; then
        echo "== $what: done before ($dir/summary.json)" >&2
        return 0
    fi
    echo "== $what -> $dir" >&2
    rm -rf "$dir"
    "$rfcl" train --run-dir "$dir" "$@" >"$dir.log" 2>&1 \
        || echo "   the run failed: $dir.log" >&2
}
