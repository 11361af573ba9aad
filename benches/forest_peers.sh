#!/usr/bin/env bash
# The LiDAR inventory against its peer: 3DFin 0.6 (PyPI `3dfin`, headless `3DFin cli`) and
# `sylva inventory` on the same real clouds, side by side: seconds, stems found, stems with a
# DBH, peak RSS.
#
#   benches/forest_peers.sh            # TreeLS pine_plot.laz (114 k points)
#   benches/forest_peers.sh --big      # and the 9.2 M-point benchmark cloud of
#                                      # ../shared/bench/make_plot10m.py (built once under target/)
#   benches/forest_peers.sh A.laz ...  # other clouds
#   benches/forest_peers.sh --single-trees  # the real single trees' heights beside 3DFin's
#
# Environment: SYLVA_REAL_DATA (default ../shared/data/real), SYLVA_BIN (a built `sylva`;
# default: `cargo build --release --bin sylva`), PEERS_VENV (default target/peers-venv).
# 3DFin runs with its shipped 3DFinconfig.ini ("default") and with settings tuned for sparse
# TLS (benches/3dfin_sparse_tls.ini, written by this script from the shipped file; the
# changes are listed in the table's notes). The Python venv is made under target/ and holds
# `3dfin` 0.6.x (which brings laspy and lazrs) and numpy.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv=${PEERS_VENV:-$root/target/peers-venv}
py=${PYTHON:-python3}

if [ ! -x "$venv/bin/python" ]; then
    echo "making the venv $venv" >&2
    "$py" -m venv "$venv"
fi
if ! "$venv/bin/python" -c "import three_d_fin, laspy, lazrs, numpy" 2>/dev/null; then
    echo "installing 3dfin 0.6.x into $venv" >&2
    "$venv/bin/pip" install -q --upgrade pip >&2 || true
    # No `laspy[lazrs]` beside it: 3dfin pins laspy ~2.5.4 and lazrs ~0.8, and asking for the
    # extra as well sends pip's resolver back through every laspy release.
    if ! "$venv/bin/pip" install -q --prefer-binary '3dfin==0.6.*' numpy >&2; then
        echo "3DFin could not be installed: 'pip install 3dfin==0.6.*' failed (output above);" \
            "only sylva is measured" >&2
    fi
fi

sylva=${SYLVA_BIN:-}
if [ -z "$sylva" ]; then
    (cd "$root" && cargo build --release --bin sylva >&2)
    sylva=$root/target/release/sylva
fi

exec "$venv/bin/python" "$root/benches/forest_peers.py" --sylva "$sylva" "$@"
