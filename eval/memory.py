"""Peak memory (max RSS) and time of each subcommand on a generated pair of large JPEGs.

    python eval/memory.py --megapixels 1 24 99 --out results/memory.json

Each command runs in its own process (one thread); the pair is the bundled example pair enlarged
to the size asked for (content looks 1.3x bigger in B).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

from localscale.evaluation.report import git_commit

ASSETS = Path(__file__).resolve().parent.parent / "localscale" / "assets"
COMMANDS = {
    "predict": ["predict", "{a}", "{b}", "-o", "{out}/predict"],
    "match": ["match", "{a}", "{b}", "-o", "{out}/match"],
    "show": ["show", "{a}", "{b}", "-o", "{out}/show"],
    "rectify": ["rectify", "{a}", "{b}", "-o", "{out}/rectify"],
    "scale": ["scale", "{a}", "{b}"],
}
# VmHWM: the peak of this process's own memory (ru_maxrss would include the parent's at fork)
_PEAK = """
import json, re, sys
from localscale.cli import main
rc = main(sys.argv[1:])
hwm = re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read())
print(json.dumps({"rc": rc, "peak_mb": int(hwm.group(1)) / 1024}))
"""


def make_pair(folder: Path, megapixels: float) -> tuple[Path, Path]:
    paths = []
    for name in ("a", "b"):
        img = cv2.imread(str(ASSETS / f"kodim01_{name}.jpg"))
        f = math.sqrt(megapixels * 1e6 / (img.shape[0] * img.shape[1]))
        big = cv2.resize(img, (round(img.shape[1] * f), round(img.shape[0] * f)), interpolation=cv2.INTER_CUBIC)
        p = folder / f"{megapixels:g}mp_{name}.jpg"
        cv2.imwrite(str(p), big, [cv2.IMWRITE_JPEG_QUALITY, 90])
        paths.append(p)
    return paths[0], paths[1]


def measure(args: list[str]) -> dict:
    t = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-c", _PEAK, *args], capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    if r.returncode != 0:
        return {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"}
    out = json.loads(r.stdout.strip().splitlines()[-1])
    return {"peak_mb": round(out["peak_mb"]), "seconds": round(time.perf_counter() - t, 2)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--megapixels", type=float, nargs="+", default=[1, 24, 99])
    p.add_argument("--commands", nargs="+", choices=list(COMMANDS), default=list(COMMANDS))
    p.add_argument("--out", default="results/memory.json")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for mp in args.megapixels:
            a, b = make_pair(Path(tmp), mp)
            for name in args.commands:
                cmd = [c.format(a=a, b=b, out=f"{tmp}/{mp:g}") for c in COMMANDS[name]]
                rows.append({"megapixels": mp, "command": name, **measure(cmd)})
                print(json.dumps(rows[-1]), file=sys.stderr)
            for f in (a, b):
                f.unlink()
    lines = [
        "| command | " + " | ".join(f"{mp:g} MP" for mp in args.megapixels) + " |",
        "|---|" + "---|" * len(args.megapixels),
    ]
    for name in args.commands:
        cells = []
        for mp in args.megapixels:
            r = next(r for r in rows if r["command"] == name and r["megapixels"] == mp)
            cells.append(r.get("error") or f"{r['peak_mb']} MB, {r['seconds']:.1f} s")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    print("\n".join(lines))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"rows": rows, "table": lines, "commit": git_commit()}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
