# Sourced by scripts/setup.sh and scripts/blender.sh: `pip_install WHO PYTHON ARGS...` runs
# `PYTHON -m pip install ARGS` and shows its progress in lines a CI log can hold: one per package
# pip fetches (its name and size, with minutes:seconds since the start) and one per local build,
# instead of pip's progress bars and its "Requirement already satisfied" lines (hundreds on a
# reinstall). pip's whole output goes to a log file; when pip fails its last lines are shown.

# pip's output in; the lines worth showing out (stderr), prefixed with WHO and the time since START;
# every line into LOG
_pip_lines() {
  local who=$1 log=$2 start=$3 line now n
  while IFS= read -r line; do
    printf '%s\n' "$line" >> "$log"
    line=${line#"${line%%[! ]*}"}  # pip indents the lines of a package
    case $line in
      *.metadata\ \(*) continue ;;  # pip reads a wheel's metadata before the wheel: one line is enough
      "Downloading "*\(*\) | "Using cached "*\(*\))
        # a mirror's full URL: its file name is what tells the package
        [[ $line =~ ^(Downloading|Using\ cached)\ (.*/)?([^/]+)$ ]] &&
          line="${BASH_REMATCH[1]} ${BASH_REMATCH[3]}" ;;
      "Processing "*)  # a wheel from a local index or --find-links: its size from the file
        n=${line#Processing }
        line="Processing ${n##*/}"
        if [ -f "$n" ]; then
          n=$(stat -c %s "$n")
          if ((n >= 1000000)); then line+=" ($(((n + 500000) / 1000000)) MB)"
          else line+=" ($(((n + 500) / 1000)) kB)"; fi
        fi ;;
      "Installing collected packages: "*)
        n=${line//[!,]/}
        n=$((${#n} + 1))
        line="installing $n package$( ((n == 1)) || echo s)" ;;
      "Building "* | "Successfully built "* | ERROR:* | error:*) ;;
      *) continue ;;
    esac
    printf -v now '%(%s)T' -1
    printf '%s: %2d:%02d  %s\n' "$who" $(((now - start) / 60)) $(((now - start) % 60)) "$line" >&2
  done
}

pip_install() {
  local who=$1 py=$2 log start end rc=0
  shift 2
  log=$(mktemp "${TMPDIR:-/tmp}/gesturedb-pip.XXXXXX")
  printf -v start '%(%s)T' -1
  # pipefail (set by the scripts): the status is pip's
  PYTHONUNBUFFERED=1 "$py" -m pip install --progress-bar off --disable-pip-version-check "$@" 2>&1 |
    _pip_lines "$who" "$log" "$start" || rc=$?
  printf -v end '%(%s)T' -1
  if [ "$rc" -ne 0 ]; then
    echo "$who: pip failed (exit $rc) after $(((end - start) / 60)) min $(((end - start) % 60)) s; the end of its" \
      "output (all of it: $log):" >&2
    tail -n 25 "$log" >&2
    return "$rc"
  fi
  echo "$who: done in $(((end - start) / 60)) min $(((end - start) % 60)) s" >&2
  rm -f "$log"
}
