"""Hostile runs of ``localscale reconstruct`` on a tiny rendered scene: kills (SIGKILL at named
points), a full disk, read-only inputs and outputs, two runs on one folder, inputs where the run
writes, photos changed between runs, names that are not UTF-8, symbolic link loops.

    OMP_NUM_THREADS=1 python eval/fault_campaign.py -o /tmp/fault_campaign --json results/fault_campaign.json
    git archive COMMIT | tar -x -C /tmp/old && python eval/fault_campaign.py -o /tmp/fc_old --code /tmp/old

Each case runs the CLI in subprocesses (``python -m localscale``; a kill point runs it through this
script's driver, which kills itself when ``module:attr`` is called the n-th time) and records:
tracebacks printed, whether an input changed, and whether the folder is consistent: a
``summary.json``, if there is one, must describe the folder (its images and registered images are
those of ``database.db`` and ``sparse/0``). Targets: no traceback, no input changed, no folder
whose summary does not describe it. The full disk and the read-only mounts need root (``mount``);
without it those cases say so. Prints the markdown table; ``--json`` writes the rows.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

#: the checkout whose ``localscale`` the runs use (``--code``)
CODE = {"root": Path(__file__).resolve().parents[1]}
FAST = ["--matcher", "sift", "--num-keypoints", "800", "--no-progress", "--num-threads", "1"]


def driver(argv: list) -> int:
    """``--kill-at module:attr:nth:before|after|sleepS ARGV...``: ``localscale ARGV`` killed at
    that call (``attr`` may be ``Class.method``), or held there ``S`` seconds.
    With ``FAULT_PID`` set, ``os.getpid`` returns it (a pid that repeats after a restart)."""
    import importlib

    if os.environ.get("FAULT_PID"):
        os.getpid = lambda: int(os.environ["FAULT_PID"])
    from localscale.cli import main

    if argv[0] == "-":
        return main(argv[1:])
    module, attr, nth, when = argv[0].split(":")
    *path, name = attr.split(".")
    owner = importlib.import_module(module)
    for part in path:
        owner = getattr(owner, part)
    real, calls = getattr(owner, name), [0]

    def killer(*args, **kwargs):
        calls[0] += 1
        if calls[0] == int(nth) and when.startswith("sleep"):  # hold the run there a while
            time.sleep(float(when[5:]))
        if calls[0] == int(nth) and when == "before":
            os.kill(os.getpid(), signal.SIGKILL)
        out = real(*args, **kwargs)
        if calls[0] == int(nth) and when == "after":
            os.kill(os.getpid(), signal.SIGKILL)
        return out

    setattr(owner, name, killer)
    return main(argv[1:])


def cli(args: list, kill: str = "", env: dict | None = None, wait: bool = True):
    """Run ``localscale reconstruct ARGS`` (killed at ``kill`` when given); a finished run's
    ``(exit code, stderr)``, or the ``Popen`` when not ``wait``."""
    env = dict(os.environ, PYTHONPATH=str(CODE["root"]), RAY_USAGE_STATS_ENABLED="0", **(env or {}))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--kill-at", kill or "-", "reconstruct", *args, *FAST]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    if not wait:
        return proc
    _, err = proc.communicate(timeout=600)
    return proc.returncode, err


def snapshot(folder: Path) -> dict:
    return {
        os.fsencode(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None) for p in sorted(folder.rglob("*"))
    }


def folder_state(out: Path) -> str:
    """``finished`` (a summary that describes the folder), ``unfinished`` (no summary) or what is wrong."""
    if not (out / "summary.json").exists():
        return "unfinished"
    import pycolmap

    summary = json.loads((out / "summary.json").read_text())
    db = pycolmap.Database.open(str(out / "database.db"))
    try:
        images = db.num_images()
    finally:
        db.close()
    model = out / "sparse" / "0"
    registered = pycolmap.Reconstruction(str(model)).num_reg_images() if model.is_dir() else 0
    if (summary["images"], summary["registered"]) != (images, registered):
        return f"INCONSISTENT: summary {summary['registered']}/{summary['images']}, folder {registered}/{images}"
    return f"finished {registered}/{images}"


def leftovers(out: Path) -> list:
    if not out.is_dir():
        return []
    return sorted(p.name for p in out.iterdir() if any(t in p.name for t in (".tmp", ".new-", ".old-", "-wal", "-shm")))


class Campaign:
    """The cases, each a method ``case_*`` returning ``(expected, observed, errors)``, in a work folder."""

    def __init__(self, work: Path):
        self.work = work
        self.scene = work / "scene"
        if not self.scene.is_dir():
            from localscale.sfm.synthetic import write_scene

            write_scene(self.scene, num_views=5, shape=(120, 160), seed=3)
        self.rows = []
        self.tracebacks = 0

    def fresh(self, name: str, views=range(4)) -> tuple:
        """``(images folder with views, OUT path)`` of a new case folder."""
        base = self.work / name
        _unmount(base)
        shutil.rmtree(base, ignore_errors=True)
        images = base / "images"
        images.mkdir(parents=True)
        for i in views:
            shutil.copy(self.scene / f"view_{i}.png", images)
        return images, base / "out"

    def run(self, args: list, **kwargs) -> tuple:
        code, err = cli(args, **kwargs)
        if "Traceback" in err:
            self.tracebacks += 1
        lines = [line for line in err.splitlines() if line.startswith(("error:", "warning:"))]
        tail = "; ".join(lines[-2:]) or (err.strip().splitlines() or [""])[-1]
        return code, f"exit {code}" + (f" ({tail[:150]})" if tail and code else ""), "Traceback" in err

    def record(self, case: str, expected: str, fn) -> None:
        t = time.time()
        try:
            observed, ok = fn()
        except Exception as e:  # a case that could not run says why
            observed, ok = f"case failed: {type(e).__name__}: {e}", False
        self.rows.append({"case": case, "expected": expected, "observed": observed, "ok": ok})
        print(f"{'ok ' if ok else 'BAD'} {case}: {observed} ({time.time() - t:.0f} s)", flush=True)


def _mount(*args) -> bool:
    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


def _unmount(base: Path) -> None:
    """Unmount what the cases mounted under ``base`` (bind mounts too, which ``os.path.ismount`` misses)."""
    with open("/proc/self/mounts") as f:
        mounted = {line.split()[1] for line in f}
    for p in (base / "out", base / "images", base / "disk"):
        if str(p) in mounted:
            subprocess.run(["umount", str(p)], capture_output=True)


# ---------------------------------------------------------------- the cases

#: kill points ``(label, module:attr:nth:when, run)``: ``run`` is ``new`` (an empty OUT), ``resume``
#: (a finished run of four views, a fifth added) or ``overwrite`` (the same with ``--overwrite``)
KILLS = [
    ("extraction (3rd image)", "localscale.sfm.extract:load_working:3:before", "new"),
    ("features.h5 write (copied, not renamed)", "localscale.sfm.h5io:shutil.copyfile:1:after", "resume"),
    ("matching (3rd pair)", "localscale.sfm.h5io:H5Writer.add:7:before", "new"),
    ("database write (3rd image)", "localscale.sfm.database:read_group:3:before", "new"),
    ("mapping", "localscale.sfm.mapping:_best_of_trials:1:before", "resume"),
    ("sparse/ swap, just before", "localscale.sfm.mapping:replace_dir:1:before", "resume"),
    ("sparse/ swap, just after", "localscale.sfm.mapping:replace_dir:1:after", "resume"),
    ("just after run.json", "localscale.sfm.reconstruction:write_json:1:after", "new"),
    ("just after summary.json", "localscale.sfm.reconstruction:write_json:2:after", "resume"),
    ("deleting our files (--overwrite)", "localscale.sfm.outdir:_remove:4:before", "overwrite"),
]


def kill_case(c: Campaign, label: str, point: str, mode: str) -> tuple:
    images, out = c.fresh("kill-" + point.replace(":", "-"), range(4))
    if mode != "new":
        assert c.run([str(images), "-o", str(out)])[0] == 0
        shutil.copy(c.scene / "view_4.png", images)
    before = snapshot(images)
    args = [str(images), "-o", str(out)] + (["--overwrite"] if mode == "overwrite" else [])
    proc_code, _, tb1 = c.run(args, kill=point)
    after_kill = folder_state(out)
    left = leftovers(out)
    code, seen, tb2 = c.run(args)  # the same command again
    state = folder_state(out)
    ok = (
        proc_code == -signal.SIGKILL
        and "INCONSISTENT" not in after_kill
        and code == 0
        and state.startswith("finished")
        and snapshot(images) == before
        and not leftovers(out)
        and not (tb1 or tb2)
    )
    killed = "killed" if proc_code == -signal.SIGKILL else f"NOT killed (exit {proc_code})"
    return f"{killed}: {after_kill}, left {len(left)} temporaries; rerun {seen}, {state}", ok


def case_pid_repeats(c: Campaign) -> tuple:
    """A kill in the database write, then a rerun with the killed run's pid (a container restart)."""
    images, out = c.fresh("pid", range(4))
    proc = cli([str(images), "-o", str(out)], kill="localscale.sfm.database:read_group:3:before", wait=False)
    proc.communicate(timeout=600)
    code, seen, tb = c.run([str(images), "-o", str(out)], env={"FAULT_PID": str(proc.pid)})
    state = folder_state(out)
    return f"rerun with pid {proc.pid}: {seen}, {state}", code == 0 and state.startswith("finished") and not tb


def case_inputs_where_run_writes(c: Campaign, what: str) -> tuple:
    images, out = c.fresh("input-" + what.replace(" ", "-"), range(4))
    assert c.run([str(images), "-o", str(out)])[0] == 0
    args = [str(images), "-o", str(out), "--overwrite"]
    if what == "images folder = OUT/sparse":
        shutil.rmtree(out)
        shutil.copytree(images, out / "sparse")
        args[0] = str(out / "sparse")
    elif what == "image linked into OUT/sparse":
        shutil.copy(images / "view_0.png", out / "sparse" / "x.png")
        os.symlink(out / "sparse" / "x.png", images / "view_9.png")
    elif what == "pairs file = OUT/pairs.txt":
        args += ["--pairs", str(out / "pairs.txt")]
    elif what == "camera file in OUT/sparse":
        (out / "sparse" / "camera.txt").write_text("1 PINHOLE 160 120 150 150 80 60\n")
        args += ["--camera", str(out / "sparse" / "camera.txt")]
    before = snapshot(out)
    code, seen, tb = c.run(args)
    return seen, code == 2 and snapshot(out) == before and "--overwrite" not in seen and not tb


def case_full_disk(c: Campaign, free_kb: int) -> tuple:
    """OUT on a 2 MB tmpfs with ``free_kb`` left; then the rerun with the room back."""
    images, _ = c.fresh(f"full-disk-{free_kb}", range(4))
    disk, out = images.parent / "disk", images.parent / "disk" / "out"
    disk.mkdir()
    if not _mount("-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)):
        return "not run: mount not allowed", True
    try:
        free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
        (disk / "filler").write_bytes(b"\0" * max(0, free - free_kb * 1024))
        before = snapshot(images)
        code, seen, tb = c.run([str(images), "-o", str(out)])
        state, left = folder_state(out), leftovers(out)
        (disk / "filler").unlink()
        code2, seen2, tb2 = c.run([str(images), "-o", str(out)])
        state2 = folder_state(out)
    finally:
        _unmount(images.parent)
    ok = code in (0, 2) and not (tb or tb2) and "INCONSISTENT" not in state and not left and snapshot(images) == before
    seen = f"{seen}, {state}, {len(left)} temporaries left; with room: {seen2}, {state2}"
    return seen, ok and (code == 0 or state == "unfinished") and state2.startswith("finished")


def case_read_only_images(c: Campaign, how: str) -> tuple:
    images, out = c.fresh("ro-images-" + how, range(4))
    before = snapshot(images)
    if how == "chmod":
        subprocess.run(["chmod", "-R", "a-w", str(images)], check=True)
    elif not (_mount("--bind", str(images), str(images)) and _mount("-o", "remount,ro,bind", str(images))):
        return "not run: mount not allowed", True
    try:
        code, seen, tb = c.run([str(images), "-o", str(out)])
        state = folder_state(out)
    finally:
        _unmount(images.parent)
        subprocess.run(["chmod", "-R", "u+w", str(images)], capture_output=True)
    return f"{seen}, {state}", code == 0 and state.startswith("finished") and snapshot(images) == before and not tb


def case_read_only_out(c: Campaign, extra: list) -> tuple:
    images, out = c.fresh("ro-out" + "".join(extra), range(4))
    assert c.run([str(images), "-o", str(out)])[0] == 0
    shutil.copy(c.scene / "view_4.png", images)
    if not (_mount("--bind", str(out), str(out)) and _mount("-o", "remount,ro,bind", str(out))):
        return "not run: mount not allowed", True
    try:
        before = snapshot(out)
        code, seen, tb = c.run([str(images), "-o", str(out), *extra])
        same = snapshot(out) == before
    finally:
        _unmount(images.parent)
    return f"{seen}, folder unchanged: {same}", code == 2 and same and not tb


def case_two_runs(c: Campaign, overlap: bool) -> tuple:
    """Two runs on one folder: started together, or the second while the first is held in mapping."""
    images, out = c.fresh("two-runs-" + ("held" if overlap else "together"), range(4))
    before = snapshot(images)
    first = cli(
        [str(images), "-o", str(out)],
        kill="localscale.sfm.mapping:_best_of_trials:1:sleep15" if overlap else "",
        wait=False,
    )
    if overlap:
        deadline = time.time() + 120
        while not (out / "database.db").exists() and time.time() < deadline:
            time.sleep(0.2)
    second = cli([str(images), "-o", str(out)], wait=False)
    results = [(p.communicate(timeout=600)[1], p.returncode)[::-1] for p in (first, second)]
    c.tracebacks += sum("Traceback" in err for _, err in results)
    codes = [code for code, _ in results]
    refused = [err for code, err in results if code == 2]
    state = folder_state(out)
    seen = f"exits {codes}" + (f" ({refused[0].strip().splitlines()[-1][:110]})" if refused else "") + f", {state}"
    ok = 0 in codes and set(codes) <= {0, 2} and state.startswith("finished") and snapshot(images) == before
    return seen, ok and (codes == [0, 2] or not overlap) and not any("Traceback" in e for _, e in results)


def case_photos_changed(c: Campaign, change: str) -> tuple:
    images, out = c.fresh("changed-" + change, range(4))
    assert c.run([str(images), "-o", str(out)])[0] == 0
    if change == "replaced":
        shutil.copy(c.scene / "view_4.png", images / "view_3.png")
    elif change == "added":
        shutil.copy(c.scene / "view_4.png", images)
    else:
        (images / "view_3.png").unlink()
        shutil.copy(c.scene / "view_4.png", images)  # four again, one of them new
    code, seen, tb = c.run([str(images), "-o", str(out)])
    if change == "replaced":
        code2, seen2, tb2 = c.run([str(images), "-o", str(out), "--overwrite"])
        state = folder_state(out)
        return f"resume: {seen}; --overwrite: {seen2}, {state}", code == 2 and code2 == 0 and state.startswith(
            "finished"
        ) and not (tb or tb2)
    state = folder_state(out)
    return f"{seen}, {state}", code == 0 and state.startswith("finished") and not tb


def case_not_utf8(c: Campaign) -> tuple:
    images, out = c.fresh("not-utf8", range(5))
    os.rename(os.fsencode(images / "view_4.png"), os.path.join(os.fsencode(images), b"k\xff002.png"))
    code, seen, tb = c.run([str(images), "-o", str(out)])
    code2, seen2, tb2 = c.run([str(images), "-o", str(out)])
    state = folder_state(out)
    return f"{seen} / rerun {seen2}, {state}", code == code2 == 0 and state.startswith("finished 4/4") and not (
        tb or tb2
    )


def case_link_loop(c: Campaign, where: str) -> tuple:
    images, out = c.fresh("loop-" + where, range(4))
    loop = images.parent / "loop"
    os.symlink(loop, loop)
    args = [str(images), "-o", str(loop)] if where == "output" else [str(loop), "-o", str(out)]
    code, seen, tb = c.run(args)
    return seen, code == 2 and not tb and not out.exists()


def cases(c: Campaign) -> list:
    """``(case, expected, function)`` of every case."""
    rows = [
        (
            f"SIGKILL at {label}, then rerun",
            "no summary that does not describe the folder; rerun finishes, no temporaries left",
            lambda a=(label, point, mode): kill_case(c, *a),
        )
        for label, point, mode in KILLS
    ]
    rows += [
        (
            "SIGKILL in database write, rerun with the same pid",
            "rerun finishes (no temporary reused)",
            lambda: case_pid_repeats(c),
        ),
        *(
            (
                f"full disk (OUT on a 2 MB tmpfs, {kb} KB free), then room",
                "one error line, exit 2, no summary, no temporaries; then finishes",
                lambda kb=kb: case_full_disk(c, kb),
            )
            for kb in (40, 200, 500, 900, 1200, 1500)
        ),
        (
            "images read-only (chmod -R a-w)",
            "run finishes, images unchanged",
            lambda: case_read_only_images(c, "chmod"),
        ),
        ("images on a read-only mount", "run finishes, images unchanged", lambda: case_read_only_images(c, "mount")),
        (
            "OUT on a read-only mount, resume",
            "one error line, exit 2, OUT unchanged",
            lambda: case_read_only_out(c, []),
        ),
        (
            "OUT on a read-only mount, --overwrite",
            "one error line, exit 2, OUT unchanged",
            lambda: case_read_only_out(c, ["--overwrite"]),
        ),
        (
            "two runs on one folder, started together",
            "one finishes; the other exits 2 ('another run') or resumes after it",
            lambda: case_two_runs(c, False),
        ),
        (
            "second run while the first is in mapping",
            "first finishes, second: exit 2 'another run', nothing written",
            lambda: case_two_runs(c, True),
        ),
        (
            "a photo replaced, then resume",
            "exit 2 ('changed'); --overwrite finishes",
            lambda: case_photos_changed(c, "replaced"),
        ),
        ("a photo added, then resume", "resume finishes 5/5", lambda: case_photos_changed(c, "added")),
        (
            "a photo removed and another added, then resume",
            "resume finishes, summary describes the folder",
            lambda: case_photos_changed(c, "removed"),
        ),
        ("file name not UTF-8 (k\\xff002.png)", "warning, skipped; run and rerun finish 4/4", lambda: case_not_utf8(c)),
        ("-o a symlink loop", "one error line, exit 2", lambda: case_link_loop(c, "output")),
        ("IMAGES a symlink loop", "one error line, exit 2, nothing written", lambda: case_link_loop(c, "images")),
    ]
    for what in (
        "images folder = OUT/sparse",
        "image linked into OUT/sparse",
        "pairs file = OUT/pairs.txt",
        "camera file in OUT/sparse",
    ):
        rows.append(
            (
                f"--overwrite with {what}",
                "one error line, exit 2, OUT unchanged, no --overwrite hint",
                lambda w=what: case_inputs_where_run_writes(c, w),
            )
        )
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("-o", "--work", default="/tmp/fault_campaign", help="work folder (its case folders are replaced)")
    p.add_argument("--json", default=None, help="write the rows (and the totals) to this JSON file")
    p.add_argument("--only", default=None, help="run the cases whose name contains this text")
    p.add_argument(
        "--code", default=None, help="a checkout of localscale to run instead of this one (e.g. an older commit)"
    )
    args = p.parse_args(argv)
    if args.code:
        CODE["root"] = Path(args.code).resolve()
    c = Campaign(Path(args.work))
    for case, expected, fn in cases(c):
        if args.only is None or args.only in case:
            c.record(case, expected, fn)
    print("\n| case | expected | observed | as expected |\n|---|---|---|---|")
    for r in c.rows:
        print(f"| {r['case']} | {r['expected']} | {r['observed']} | {'yes' if r['ok'] else 'NO'} |")
    bad = [r["case"] for r in c.rows if not r["ok"]]
    print(f"\n{len(c.rows) - len(bad)}/{len(c.rows)} as expected; tracebacks: {c.tracebacks}")
    if args.json:
        from localscale.core.outputs import write_text

        totals = {"cases": len(c.rows), "as_expected": len(c.rows) - len(bad), "tracebacks": c.tracebacks}
        write_text(args.json, json.dumps({"rows": c.rows, "totals": totals}, indent=2) + "\n")
    return 1 if bad or c.tracebacks else 0


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--kill-at":
        sys.exit(driver(sys.argv[2:]))
    sys.exit(main())
