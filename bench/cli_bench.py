"""Seconds per command (``make bench``): each CLI command's wall time as a ratio to a bare
``python -c "import duckdb"`` measured in the same run, and the share of a label round (ingest the
answer, resume the clip) spent outside stage work: by ``cadestate labels ingest`` with Prefect's
ephemeral API and with `cadestate server start`, and in the annotation app (``cadestate annotate``,
a long-lived process) with the server up.

Budgets (issue "Seconds per command"): ``--help`` and ``labels schema`` within 1.5x of the bare
baseline; ``sql``, ``tables`` and ``status`` on the demo warehouse within 3x; a label round with the
server up spends under 20 % of its wall time outside stage work (``server_ok`` for the command,
``app_server_ok`` for the app).
"""

from __future__ import annotations

import datetime as dt
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from statistics import median

from warehouse import Warehouse

REPEATS = 7
APP_BOXES = (0.3, 0.5, 0.35, 0.45, 0.32, 0.52, 0.38, 0.48, 0.34, 0.42)
"""Left edges of the box each app round's manual-track answer draws (a new answer each round, so
its stage and what follows rerun): the first round warms the app up, the other nine are measured
(a round's share moves by a few points with the machine's load; the median of nine, less)."""
BUDGETS = {"--help": 1.5, "labels schema correspondences": 1.5, "config show": 3.0,
           "sql 'SELECT count(*) FROM frames'": 3.0, "tables": 3.0, "status": 3.0}
"""Command -> the largest ratio to the bare baseline it may take."""
BASELINE = "import duckdb"


def command_env() -> dict[str, str]:
    """This process's environment without Prefect's settings: each command finds its own Prefect."""
    return {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}


def children_cpu_s() -> float:
    """CPU seconds (user + system) of every child process that has ended so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed(args: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system, of the child) of one run of ``args`` (output discarded)."""
    cpu0, t0 = children_cpu_s(), time.perf_counter()
    subprocess.run(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=command_env(), check=False)
    return time.perf_counter() - t0, children_cpu_s() - cpu0


def measure(commands: dict[str, list[str]], repeats: int = REPEATS) -> dict[str, dict[str, float]]:
    """Median wall and CPU seconds of each of ``commands`` (name -> argv), run in turn ``repeats``
    times (interleaved, so a change of load on the machine touches every command alike)."""
    samples: dict[str, list[tuple[float, float]]] = {name: [] for name in commands}
    for _ in range(repeats):
        for name, args in commands.items():
            samples[name].append(timed(args))
    return {name: {"wall_s": median(w for w, _ in runs), "cpu_s": median(c for _, c in runs)}
            for name, runs in samples.items()}


def command_ratios(warehouse: Path, repeats: int = REPEATS) -> dict:
    """Wall and CPU time of each command of :data:`BUDGETS` on ``warehouse`` as ratios to the bare
    baseline (``python -c "import duckdb"``), measured interleaved with it (see :func:`ratios`)."""
    import shlex

    cli = [sys.executable, "-m", "cadestate", "-w", str(warehouse)]
    commands = {BASELINE: [sys.executable, "-c", BASELINE],
                **{command: [*cli, *shlex.split(command)] for command in BUDGETS}}
    return ratios(measure(commands, repeats), BUDGETS, repeats)


def ratios(times: dict[str, dict[str, float]], budgets: dict[str, float], repeats: int) -> dict:
    """Each command's wall and CPU ratios to the baseline's in ``times`` (as :func:`measure` gives
    them) next to its budget; a command is ``ok`` when both are within it, and ``budgets_ok`` is
    False when any command is not."""
    base = times[BASELINE]
    rows = {}
    for command, budget in budgets.items():
        wall, cpu = times[command]["wall_s"] / base["wall_s"], times[command]["cpu_s"] / base["cpu_s"]
        rows[command] = {"s": round(times[command]["wall_s"], 3), "ratio": round(wall, 2), "cpu_ratio": round(cpu, 2),
                         "budget": budget, "ok": wall <= budget and cpu <= budget}
    return {"baseline_import_duckdb_s": round(base["wall_s"], 3), "baseline_cpu_s": round(base["cpu_s"], 3),
            "repeats": repeats, "commands": rows, "budgets_ok": all(r["ok"] for r in rows.values())}


def ratio_lines(ratios: dict) -> list[str]:
    """One line per command: its wall and CPU ratios next to its budget, and whether it is within."""
    lines = [f"baseline python -c {BASELINE!r}: {ratios['baseline_import_duckdb_s']:.3f} s wall, "
             f"{ratios['baseline_cpu_s']:.3f} s CPU (median of {ratios['repeats']})"]
    for command, row in ratios["commands"].items():
        verdict = "ok" if row["ok"] else "OVER BUDGET"
        lines.append(f"{command:<40} wall {row['ratio']:5.2f}x  cpu {row['cpu_ratio']:5.2f}x  "
                     f"budget {row['budget']:.1f}x  {verdict}")
    return lines


def _round_text(wall_s: float, share: float, target: bool) -> str:
    """A label round's (or rounds') wall time and share outside stage work, with the 20 % target's verdict."""
    verdict = f"  target < 20 %  {'ok' if share < 0.2 else 'OVER TARGET'}" if target else ""
    return f"{wall_s:.2f} s, {100 * share:.0f} % outside stage work{verdict}"


def round_lines(rounds: dict) -> list[str]:
    """One line per label round of :func:`label_rounds`: its wall time and share outside stage
    work, next to the 20 % target where one applies (with the server up)."""
    lines = []
    for key, what, target in (("ephemeral", "labels ingest, ephemeral Prefect", False),
                              ("server", "labels ingest, server up", True), ("app_server", "annotation app, server up", True)):
        r = rounds.get(key, {})
        if "outside_share" not in r:
            lines.append(f"label round, {what}: {'; '.join(r.get('error', ['not measured']))}")
            continue
        of = f" (median of {r['rounds']})" if "rounds" in r else ""
        lines.append(f"label round, {what}{of}: {_round_text(r['wall_s'], r['outside_share'], target)}")
    return lines


def demo_round_line(demo: dict) -> str:
    """The line of ``make run``'s demo clip's label rounds through the app
    (:func:`bench.annotate_resume.run_demo`): all rounds' wall time and share outside stage work."""
    rounds = demo.get("all_rounds")
    if not rounds or rounds.get("outside_share") is None:
        return f"label rounds, demo clip in the annotation app: {demo.get('answer_to_next_task', demo.get('skipped', 'not measured'))}"
    return (f"label rounds, demo clip in the annotation app ({len(demo['rounds'])} rounds): "
            f"{_round_text(rounds['wall_s'], rounds['outside_share'], True)}")


def _manual_label(task: Path, answers: list) -> dict:
    doc = json.loads(task.read_text())
    return {"format": "cadestate-label/1", "kind": "manual_track", "clip": doc["clip"], "task_id": doc["task_id"],
            "annotator": "bench", "created_at": dt.datetime.now(dt.timezone.utc).isoformat(), "answers": answers}


def _round(cli: list[str], wh: Warehouse, label: dict, folder: Path) -> dict:
    """Ingest one label file (resuming its clip) and split the wall time into stage work and the rest."""
    path = folder / f"round-{time.time_ns()}.json"
    path.write_text(json.dumps(label))
    start = dt.datetime.now(dt.timezone.utc)
    t0 = time.perf_counter()
    done = subprocess.run([*cli, "labels", "ingest", str(path), "--no-progress"], capture_output=True, text=True, env=command_env())
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1:] or ["failed"]}
    return split_round(wh, start, wall)


def split_round(wh: Warehouse, start: dt.datetime, wall: float) -> dict:
    """A round of ``wall`` seconds that began at ``start``: its stage work (the stage runs started
    since) and the share of the wall time outside it."""
    runs = [r for r in wh.read("runs").to_pylist() if r["started_at"] >= start]
    stage = sum(float(r["duration_s"] or 0.0) for r in runs)
    return {"wall_s": round(wall, 2), "stage_s": round(stage, 2), "stage_runs": len(runs),
            "outside_share": round(1 - stage / wall, 3)}


def _app_round(client, wh: Warehouse, label: dict) -> dict:
    """Post one answer to the annotation app through ``client`` (an ``httpx.Client`` on its URL,
    one connection kept alive, as a page's) and wait, as its page does (``?wait=``), until the
    clip's stages have run (its next task is ready; the record in Prefect that follows is not the
    annotator's wait, :mod:`cadestate.webapp.resume`); the wall time split as :func:`split_round`
    splits it. Starts once the previous round's record is over."""
    view = f"/api/clips/{label['clip']}?wait=30"
    while (resume := client.get(view).json()["resume"])["state"] in ("queued", "running", "recording"):
        time.sleep(0.05)  # the last round is still being recorded in Prefect: not this round's time
    runs_before = resume["runs"]
    start = dt.datetime.now(dt.timezone.utc)
    t0 = time.perf_counter()
    posted = client.post("/api/answers", json=label)
    if posted.status_code != 200:
        return {"error": [posted.text[:200]]}
    while (resume := client.get(view).json()["resume"])["runs"] <= runs_before or resume["state"] in ("queued", "running"):
        pass  # the app answers when the resume has ended (or after 30 s)
    return {**split_round(wh, start, time.perf_counter() - t0), "resume": resume["message"]}


def app_rounds(cli: list[str], wh: Warehouse, labels: list[dict]) -> dict:
    """Label rounds through the annotation app (``cadestate annotate``, one long-lived process, as
    annotators work): the first answer of ``labels`` warms the app up (its first resume imports the
    stages and starts Prefect's client), each later one is a measured round; the round of median
    share outside stage work is reported, with every round's share (one round alone swings with
    the machine's load). The client keeps one connection, as a page does (a new ``httpx`` client
    per request costs ~20 ms of its own setup, which a round is not)."""
    import httpx

    from flows.server import free_port

    port = free_port("127.0.0.1")
    app = subprocess.Popen([*cli, "annotate", "--port", str(port)], stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL, env=command_env())
    url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=url, timeout=60) as client:
            for _ in range(600):
                try:
                    client.get("/api/clips", timeout=5)
                    break
                except httpx.TransportError:
                    time.sleep(0.1)
            else:
                return {"error": [f"cadestate annotate did not answer on {url} within a minute"]}
            rounds = [_app_round(client, wh, label) for label in labels]
    finally:
        app.terminate()
        app.wait(30)
    measured = rounds[1:]
    failed = [r for r in measured if "error" in r]
    if failed:
        return {**failed[0], "warm_up": rounds[0]}
    typical = sorted(measured, key=lambda r: r["outside_share"])[len(measured) // 2]
    return {**typical, "rounds": len(measured), "outside_shares": [r["outside_share"] for r in measured],
            "walls_s": [r["wall_s"] for r in measured], "warm_up": rounds[0]}


def label_rounds(video: Path, cameras: Path) -> dict:
    """One label round on a val clip in ephemeral mode, then one with the server up, then one in the
    annotation app with the server up (each round gives the manual-track task a different answer,
    so its stage and what follows rerun)."""
    with tempfile.TemporaryDirectory(prefix="cadestate-bench-") as tmp:
        root = Path(tmp) / "w"
        cli = [sys.executable, "-m", "cadestate", "-w", str(root)]
        subprocess.run([*cli, "ingest", str(video), str(cameras), "--split", "val", "--no-progress"],
                       capture_output=True, env=command_env(), check=True)
        wh = Warehouse(root)
        [task] = sorted((root / "label_tasks").rglob("*.manual_track.*.json"))
        frame = json.loads(task.read_text())["keyframes"][0]["timestamp_us"]
        classes = json.loads(task.read_text())["classes"] or ["chair"]
        def drawn(x: float) -> list[dict]:
            return [{"label": classes[0], "boxes": [{"timestamp_us": frame, "box": [x, 0.4, x + 0.2, 0.6]}]}]

        ephemeral = _round(cli, wh, _manual_label(task, []), Path(tmp))
        subprocess.run([*cli, "server", "start", "--port", "0"], capture_output=True, env=command_env(), check=True)
        try:
            served = _round(cli, wh, _manual_label(task, drawn(0.4)), Path(tmp))
            app = app_rounds(cli, wh, [_manual_label(task, drawn(x)) for x in APP_BOXES])
        finally:
            subprocess.run([*cli, "server", "stop"], capture_output=True, env=command_env())
    return {"ephemeral": ephemeral, "server": served, "app_server": app,
            "server_ok": "outside_share" in served and served["outside_share"] < 0.2,
            "app_server_ok": "outside_share" in app and app["outside_share"] < 0.2}


def demo_warehouse(source: Path, dest: Path, clip: str | None = None) -> tuple[Path, str]:
    """The demo warehouse the command budgets are stated on, under ``dest``: the tables of
    ``source`` (the default warehouse) with its CAD libraries and one clip, ``clip`` or make run's
    demo clip when it has it, else its first (``make bench`` also runs its benchmarks' clips into
    that warehouse: `status --stages` prints a row per clip and stage, ~0.5 s of table rendering
    for 28 clips). Copied: Parquet files only, no media, catalog or Prefect home. Returns it and the clip."""
    import shutil

    from bench.annotate_resume import DEMO_SEED
    from bench.benchmark import clip_name

    wh = Warehouse(source)
    clips, demo = wh.partitions("clips"), clip_name(DEMO_SEED, 0)
    clip = clip or (demo if demo in clips else clips[0] if clips else "")
    keep = {*wh.partitions("cad_models"), clip}
    for table_dir in sorted((source / "tables").iterdir()):
        for entry in table_dir.iterdir():
            if entry.is_dir() and "=" in entry.name and entry.name.split("=", 1)[1] not in keep:
                continue
            target = dest / "tables" / table_dir.name / entry.name
            target.parent.mkdir(parents=True, exist_ok=True)
            (shutil.copytree if entry.is_dir() else shutil.copy2)(entry, target)
    return dest, clip


def run(warehouse: Path = Path("data/warehouse")) -> dict:
    """The command ratios on the demo warehouse (:func:`demo_warehouse` of ``warehouse``) and the
    label rounds on a generated clip of the demo's size (138 camera lines, 640x360)."""
    from bench.demo_clip import DemoClipSpec, make_demo_clip

    with tempfile.TemporaryDirectory(prefix="cadestate-bench-demo-") as tmp:
        demo, clip = demo_warehouse(warehouse, Path(tmp) / "w")
        out = {"commands": {**command_ratios(demo), "warehouse": f"{warehouse}: its CAD libraries and clip {clip}"}}
    with tempfile.TemporaryDirectory(prefix="cadestate-bench-clip-") as tmp:
        clip = make_demo_clip(Path(tmp), DemoClipSpec(name="round", num_video_frames=276, seed=3))
        out["label_round"] = label_rounds(clip.video_path, clip.cameras_path)
    return out


def main() -> int:
    """Run :func:`run`, print its numbers and each command's ratios next to its budget; 1 when a
    command missed its budget."""
    result = run()
    print(json.dumps(result, indent=2))
    print("\n".join(ratio_lines(result["commands"]) + round_lines(result["label_round"])))
    return 0 if result["commands"]["budgets_ok"] else 1


if __name__ == "__main__":
    from bench.script_args import no_arguments

    no_arguments(__doc__)
    sys.exit(main())
