"""Run every benchmark script in this folder in turn (``make bench``)."""

import subprocess
import sys
from pathlib import Path

here = Path(__file__).parent
scripts = sorted(p for p in here.glob("*.py") if p.name not in {"run_all.py"})
status = 0
for s in scripts:
    print(f"\n=== {s.name} ===", flush=True)
    r = subprocess.run([sys.executable, str(s)], cwd=here.parent)
    status |= r.returncode
sys.exit(status)
