#!/bin/sh
# vigproc-bqm.sh: vigproc as a digiKam Batch Queue Manager "Custom Script" step.
#
# Do not paste "$INPUT"/"$OUTPUT" into a digiKam script yourself: digiKam replaces
# them *textually* with the file name between double quotes before running the
# script with /bin/sh -c, so a file named  a$(rm -rf ~).jpg  runs that command.
# Generate the BQM script with make-bqm-script.sh instead: it hands the two names to
# this adapter inside quoted here-documents (the shell expands nothing there), on
# file descriptors 3 (input) and 4 (output), ended by a random delimiter.
#
# Also usable directly:  vigproc-bqm.sh INPUT OUTPUT
#
# Environment:
#   VIGPROC_MODE        correct (default): write the corrected image to $OUTPUT
#                       (set the tool's Output Image Type to TIFF; 16-bit linear);
#                       check: copy $INPUT to $OUTPUT unchanged and report the
#                       forensic verdict (digiKam's log shows the JSON answer).
#   VIGPROC_COMMAND     the vigproc program (default: vigproc on PATH)
#   VIGPROC_REPORT_DIR  also keep each JSON sidecar in this folder (check mode)
#   VIGPROC_PROFILE_DB  the profile store vigproc uses
#
# Exit status: vigproc hook's (0 ok; 2 usage; 3-9 the file's error; 70 internal);
# digiKam stops the queue on a non-zero status.
set -u

die() {
    printf 'vigproc-bqm: %s\n' "$1" >&2
    exit "${2:-2}"
}

# The path digiKam wrote between double quotes into a here-document on fd $1.
from_fd() {
    # the trailing x keeps newlines at the end of the name from being stripped
    v=$(cat <&"$1"; printf x) || die "cannot read file descriptor $1"
    v=${v%x}
    v=${v%"
"}
    case $v in
        \"*\") ;;
        *) die "file descriptor $1 does not hold a quoted path (is the BQM script from make-bqm-script.sh?)" ;;
    esac
    v=${v#\"}
    v=${v%\"}
    [ -n "$v" ] || die "empty path on file descriptor $1"
    printf '%sx' "$v"
}

if [ $# -eq 2 ]; then
    input=$1
    output=$2
elif [ $# -eq 0 ] && { true <&3 && true <&4; } 2>/dev/null; then
    input=$(from_fd 3) || exit $?
    input=${input%x}
    output=$(from_fd 4) || exit $?
    output=${output%x}
else
    die "usage: vigproc-bqm.sh INPUT OUTPUT, or the BQM script made by make-bqm-script.sh"
fi

vigproc=${VIGPROC_COMMAND:-vigproc}
mode=${VIGPROC_MODE:-correct}

case $mode in
    correct)
        # exactly $OUTPUT, written atomically; its suffix must be .tif/.tiff
        exec "$vigproc" hook --mode correct --output-format tiff16 --output-file="$output" -- "$input"
        ;;
    check)
        cp -- "$input" "$output" || die "cannot copy the input to the output" 5
        if [ -n "${VIGPROC_REPORT_DIR:-}" ]; then
            exec "$vigproc" hook --mode check --output="$VIGPROC_REPORT_DIR" -- "$input"
        fi
        exec "$vigproc" hook --mode check -- "$input"
        ;;
    *)
        die "VIGPROC_MODE must be correct or check, not '$mode'"
        ;;
esac
