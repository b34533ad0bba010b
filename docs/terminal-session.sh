#!/bin/bash
# run under script(1); each command's progress goes to the terminal (stderr), tables to files
# usage: script -qc docs/terminal-session.sh session.log   (OUT=DIR for the outputs)
OUT=${OUT:-/tmp/spctool-session}; mkdir -p "$OUT"
D=$(dirname "$0")/../fixtures/demo
rm -rf $OUT/cold $OUT/demo $OUT/world $OUT/run1
echo '$ NUMBA_CACHE_DIR=<empty> spctool -C demo register P000000001A1 > reg.txt'
NUMBA_CACHE_DIR=$OUT/cold spctool -C $D register P000000001A1 > $OUT/reg.txt
echo '$ spctool warmup'
NUMBA_CACHE_DIR=$OUT/cold spctool warmup
echo '$ spctool -C demo render P000000001A1 -o render.png'
spctool -C $D render P000000001A1 -o $OUT/render.png
echo '$ spctool demo --copy-to demo && spctool -C demo make-maplets --tile 0.06 --scale 0.0005 --qsz 24 > maplets.txt'
spctool demo --copy-to $OUT/demo && spctool -C $OUT/demo make-maplets --tile 0.06 --scale 0.0005 --qsz 24 > $OUT/maplets.txt
echo '$ spctool -C demo batch --out-dir run1 > summary.txt'
spctool -C $D batch --out-dir $OUT/run1 > $OUT/summary.txt
echo '$ spctool simulate --example > world.toml && spctool simulate world.toml world > truth.txt'
spctool simulate --example > $OUT/world.toml && spctool simulate $OUT/world.toml $OUT/world > $OUT/truth.txt
echo '$ spctool demo > demo.txt'
spctool demo > $OUT/demo.txt
echo '$ spctool montecarlo --preset s16-50m --samples 5 --scene s16.npz > mc.txt'
spctool montecarlo --preset s16-50m --samples 5 --scene $OUT/s16.npz > $OUT/mc.txt
echo done
