#!/usr/bin/env bash
# Issue 38's CLI-level defects, reproduced with a given bhcl: run once with main's build and once
# with the fixed one (outputs: main.txt, fixed.txt beside this script).
# Usage: bench/results/issue38/repro.sh BHCL_BINARY
set -u
bhcl=$1
d=$(mktemp -d /tmp/bhcl_issue38_XXXX)
export POCL_MAX_PTHREAD_COUNT=2
/usr/bin/python3 -c "
import struct, random
random.seed(1)
open('$d/p.f32','wb').write(b''.join(struct.pack('<3f', random.random(), random.random(), random.random()) for _ in range(2000)))"
knn() { "$bhcl" knn --method blockhash --points "$d/p.f32" --queries "$d/p.f32" --k 4 --quiet "$@" 2>&1 | tail -1; echo "  status ${PIPESTATUS[0]}"; }
echo "== 250-byte output name"
knn --out-ids "$d/$(printf 'n%.0s' $(seq 250))" --out-dist2 /dev/null
echo "== PID-1-style stale temporary of this run's PID cannot be simulated from outside; see tests/hostile_round4_tests.cpp"
echo "== --device 0:99999999999999999999"
"$bhcl" devices --device 0:99999999999999999999 2>&1 | sed -n 1p; echo "  status ${PIPESTATUS[0]}"
echo "== BHCL_DEVICE=0:99999999999999999999"
BHCL_DEVICE=0:99999999999999999999 "$bhcl" knn --method blockhash --points "$d/p.f32" --queries "$d/p.f32" --k 4 --out-ids /dev/null --out-dist2 "$d/d2.f32" 2>&1 | sed -n 1p
echo "== text point file with 3.4028235e+38"
printf '3.4028235e+38 0 0\n1 2 3\n' > "$d/flt.txt"
"$bhcl" knn --points "$d/flt.txt" --queries "$d/flt.txt" --k 1 --method bruteforce --out-ids /dev/null --out-dist2 "$d/d2.f32" --quiet 2>&1 | tail -1; echo "  status ${PIPESTATUS[0]}"
echo "== grid index with its cell side changed and the checksum recomputed"
"$bhcl" knn --method blockhash --points "$d/p.f32" --queries "$d/p.f32" --k 8 --save-index "$d/g.bhidx" --out-ids "$d/ids_ref.i32" --out-dist2 /dev/null --quiet > /dev/null 2>&1
/usr/bin/python3 - "$d/g.bhidx" <<'PY'
import struct, sys
p = sys.argv[1]; d = bytearray(open(p, 'rb').read())
h = struct.unpack_from('<f', d, 48)[0]; struct.pack_into('<f', d, 48, h * 1.5)
def fnv(b, x=0xcbf29ce484222325):
    for c in b: x = ((x ^ c) * 0x100000001b3) & 0xffffffffffffffff
    return x
struct.pack_into('<Q', d, 132, fnv(d[140:], fnv(d[:132])))
open(p + '.bad', 'wb').write(bytes(d))
PY
"$bhcl" knn --method blockhash --points "$d/p.f32" --queries "$d/p.f32" --k 8 --load-index "$d/g.bhidx.bad" --out-ids "$d/ids_bad.i32" --out-dist2 /dev/null --quiet 2>&1 | tail -1; echo "  status ${PIPESTATUS[0]}"
if [ -f "$d/ids_bad.i32" ]; then
  /usr/bin/python3 -c "
import numpy as np
a = np.fromfile('$d/ids_ref.i32', np.int32).reshape(-1, 8); b = np.fromfile('$d/ids_bad.i32', np.int32).reshape(-1, 8)
print('  rows differing from the saved index:', int(np.any(a != b, axis=1).sum()), 'of', len(a))"
fi
echo "== grid index whose id bound says 2^31 - 2 (checksum recomputed), under ulimit -v 3 GiB"
/usr/bin/python3 - "$d/g.bhidx" <<'PY'
import struct, sys
p = sys.argv[1]; d = bytearray(open(p, 'rb').read())
struct.pack_into('<Q', d, 84, 2**31 - 2)
def fnv(b, x=0xcbf29ce484222325):
    for c in b: x = ((x ^ c) * 0x100000001b3) & 0xffffffffffffffff
    return x
struct.pack_into('<Q', d, 132, fnv(d[140:], fnv(d[:132])))
open(p + '.bound', 'wb').write(bytes(d))
PY
(ulimit -v 3145728; "$bhcl" knn --method blockhash --points "$d/p.f32" --queries "$d/p.f32" --k 8 --load-index "$d/g.bhidx.bound" --out-ids "$d/ids_b.i32" --out-dist2 /dev/null --quiet 2>&1 | tail -1; echo "  status ${PIPESTATUS[0]}")
echo "== render --out /dev/null"
rm -f /dev/null.png
"$bhcl" render --out /dev/null --photons 2000 --size 16x16 --quiet 2>&1 | tail -1; echo "  status ${PIPESTATUS[0]}"
if [ -e /dev/null.png ]; then echo "  /dev/null.png created: $(stat -c %F /dev/null.png)"; rm -f /dev/null.png; else echo "  no /dev/null.png"; fi
echo "== SIGTERM during knn (shell status; whether it lands mid-write is timing: the doctest is the check)"
/usr/bin/python3 -c "
import numpy as np
np.random.default_rng(1).random((400000, 3)).astype(np.float32).tofile('$d/big.f32')"
"$bhcl" knn --method bruteforce --points "$d/big.f32" --queries "$d/big.f32" --k 64 --out-ids "$d/sig.i32" --out-dist2 "$d/sig.f32" --quiet & pid=$!
sleep 4; kill -TERM $pid 2>/dev/null; wait $pid; echo "  status $?  temporaries left: $(ls -a "$d" | grep -c tmp)"
rm -rf "$d"
