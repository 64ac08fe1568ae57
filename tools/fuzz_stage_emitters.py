"""Process CPU of ``fsjax fuzz`` with the stage programs compiled one way or the other.

    XLA_FLAGS=--xla_backend_optimization_level=0 python tools/fuzz_stage_emitters.py level0 DIR
    XLA_FLAGS=--xla_backend_optimization_level=0 python tools/fuzz_stage_emitters.py fast DIR

``level0``: the fuzzer's setting (default emitters, XLA level 0); ``fast``:
``fsjax._linalg.FAST_COMPILE`` (older emitters at level 2). 20 chains, seed 0, one worker, a new
compile cache under ``DIR`` (remove it between runs for a cold start). Run the two side by side
and compare the printed CPU (docs/fuzz.md).
"""

import resource
import sys
import time

import fsjax.fuzz._run as R
from fsjax._linalg import FAST_COMPILE
from fsjax.cli import main

mode, out = sys.argv[1], sys.argv[2]
if mode == "fast":
    R.STAGE_COMPILER_OPTIONS = dict(FAST_COMPILE)
elif mode != "level0":
    raise SystemExit("fuzz_stage_emitters: argument 'mode' must be 'level0' or 'fast'")
w = time.perf_counter()
rc = main(["fuzz", "--chains", "20", "--length", "6", "--seed", "0", "--workers", "1",
           "--compile-cache", f"{out}/cache-{mode}", "--out", f"{out}/out-{mode}"])
ru = resource.getrusage(resource.RUSAGE_SELF)
print(f"MODE {mode} stage_opts={R.STAGE_COMPILER_OPTIONS} cpu={ru.ru_utime + ru.ru_stime:.1f}s "
      f"wall={time.perf_counter() - w:.1f}s rc={rc}", flush=True)
