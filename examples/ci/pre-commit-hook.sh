#!/usr/bin/env bash
# pre-commit hook of .pre-commit-config.yaml (next to this file): runs `drake-cert ARGS...`
# from a virtual environment of its own, made on first use by a pip install of this repository
# (editable, so it runs the code being committed) and made again when pyproject.toml or
# constraints.txt change. DRAKE_CERT_HOOK_VENV: where that environment lives (default: one
# per clone under ~/.cache/drake-cert-hook); PYTHON: the interpreter to make it with
# (Python 3.11; default python3.11).
set -euo pipefail
root=$(git rev-parse --show-toplevel)
clone_id=$(printf '%s' "$root" | cksum | cut -d' ' -f1)
venv=${DRAKE_CERT_HOOK_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/drake-cert-hook/$clone_id}
stamp="$venv/.installed"
if [ ! -x "$venv/bin/drake-cert" ] || [ "$root/pyproject.toml" -nt "$stamp" ] \
        || [ "$root/constraints.txt" -nt "$stamp" ]; then
    echo "drake-cert hook: installing $root into $venv" >&2
    "${PYTHON:-python3.11}" -m venv "$venv"
    "$venv/bin/python" -m pip install --quiet \
        --extra-index-url https://download.pytorch.org/whl/cpu \
        -c "$root/constraints.txt" -e "$root"
    touch "$stamp"
fi
exec "$venv/bin/drake-cert" "$@"
