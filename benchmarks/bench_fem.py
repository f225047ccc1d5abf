"""FEM benchmark: warpblob's implicit co-rotational FEM vs Newton and pbatoolkit on the same meshes.

Run:  python benchmarks/bench_fem.py [--models beam,tumor] [--sizes 10000,50000,200000] [--preconditioner P]
      [--peers newton,pbat] [--threads 1,2] [--budget 300] [--quick] [--json PATH]

The peers go in a virtual environment of their own (newton may want another
warp-lang than the main environment's): ``python -m venv VENV &&
VENV/bin/pip install -e . newton pbatoolkit``, then run this script with
``VENV/bin/python``.

Scenes (every solver gets the same nodes, tets, fixed nodes and material):

* ``beam``: the 1.0 x 0.2 x 0.2 m cantilever, x = 0 face fixed, gravity -z
  9.81 m/s^2, E = 1e7 Pa, nu = 0.3, rho = 1000 kg/m^3, a structured mesh
  (``warpblob.mesh.box_tetmesh``, six tets per cube) of about each size.
  Reference tip deflection: Euler-Bernoulli ``q L^4 / (8 E I)`` plus the
  Timoshenko shear term ``q L^2 / (2 kappa G A)`` (``q = rho g A``,
  ``kappa = 5/6``, ``G = E / (2 (1 + nu))``), 38.3 mm (3.8% of L). Linear
  tets are stiff on coarse meshes (locking), so the static linear FEM
  solution of the same mesh (scipy, direct or CG) is reported beside it:
  ``err ref`` is the error against the analytic deflection, ``err mesh``
  against the same mesh's static solution, that is the solver's own error.
* ``tumor``: ``wb.tetrahedralize(wb.scenes.tumor(), cellsize=h)`` with ``h``
  tuned to each size, the nodes in the lowest 15% of x fixed, gravity -z,
  E = 1e6 Pa (a softer tissue, sag about 9% of its size), nu = 0.3,
  rho = 1000 kg/m^3; deflection = mean z sag of the nodes in the highest 10%
  of x, against the mesh's static linear solution.

Timing: each solver runs in its own process (``--worker``), one frame =
``1/60`` s of simulated time (a peer's substeps and iterations inside it);
two frames warm (compilation, first touch) are not timed, then ``--repeat``
frames are timed one by one by the wall clock around the solver's whole
step call. A frame's cost depends on the state (CG iterations), so the
figure is the median timed frame, not the best (the best is in the JSON);
two timed frames only when a frame takes over 5 s. warpblob's per-stage
milliseconds are its ``Simulation.stats`` of that median frame.

Accuracy: after the timed frames the run continues, every solver's velocities
scaled by ``exp(-20 / 60)`` between frames (the same mass-proportional drag
for all, 20 1/s, about critical for the beam's first mode; it does not move
the static equilibrium), until the tip moves slower than 0.1% of the
reference deflection per second for five frames in a row (``rest``), or
``--frames`` frames have run, or ``--budget`` seconds have passed; the
deflection is read then. A run is stable when no step raised, every position
stayed finite and no node moved more than twice the model's size (a solver
can be stable and still collapse: Newton's and pbatoolkit's VBD at one
substep sag tens of times too far; the error columns show it).

Equal accuracy: at the smallest size of each ``--ladder-models`` scene each
peer climbs a ladder of settings of increasing cost (``LADDERS``) until its
``err mesh`` is at most ``max(--match, warpblob's err mesh)``; that rung is
its "matched" setting. At the larger sizes the matched setting's substeps are
scaled by the cube root of the tet-count ratio (the explicit solver's CFL
rule: substeps ~ 1 / h) and timed, its error measured where the budget
allows. Matching on the analytic error would reward an unconverged solver
whose softness cancels the mesh's locking (VBD at 400 substeps lands within
6% of the analytic deflection while 4% softer than its own mesh), hence the
mesh reference. Every peer's default setting (one substep of 1/60 s) is run
at every size (to rest on the smallest mesh, the timed frames only on the
larger ones): it tells whether the peer is stable at dt = 1/60 and how far
off it is there. ``x wb`` is a row's milliseconds over warpblob's on the
same mesh at the same thread count (one thread for Newton).

Threads: warpblob (``threads=``) and pbatoolkit (TBB, held to the cores by
the process's CPU affinity) run at each ``--threads`` count; Newton's
solvers run their Warp CPU kernels on one thread, so they run once.

Writes benchmarks/results/bench_fem.json (quick runs: only with ``--json``)
with the versions, machine, load average before and after, the references,
the ladders and every row. Needs newton and pbatoolkit installed beside
warpblob (a missing peer is skipped with a note); see ``_fem_peers.py`` for
how each peer is set up and its material parameters mapped.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _common import Run, arguments, table  # noqa: E402
from _fem_peers import ADAPTERS, GROUPS, Problem, versions  # noqa: E402

FRAME_DT = 1.0 / 60.0
DRAG = 20.0  # 1/s, the velocity scaling between frames
TARGET_MS = 16.0  # per frame at about 10K tets on two cores (the goal)
REST_SPEED = 1e-3  # at rest: tip speed below this fraction of the reference deflection per second
TIMING_FEM = ("wall clock (time.perf_counter) around each frame's step calls; warm (two frames excluded); "
              "the median of N = repeat timed frames")
BEAM = {"length": 1.0, "width": 0.2, "young": 1e7, "poisson": 0.3, "density": 1000.0, "g": 9.81}
TUMOR = {"young": 1e6, "poisson": 0.3, "density": 1000.0, "fixed": 0.15, "probe": 0.10}
#: the peers' default settings (one frame = one solver step of 1/60 s), the stability check at dt = 1/60
DEFAULTS = {
    "newton-vbd": {"substeps": 1, "iterations": 10},
    "newton-xpbd": {"substeps": 1, "iterations": 10},
    "newton-semi": {"substeps": 1},
    "pbat-vbd": {"substeps": 1, "iterations": 10},
}
#: the equal-accuracy ladders, cheapest first (VBD converges per substep far better than per iteration)
LADDERS = {
    "newton-vbd": [{"substeps": s, "iterations": 1} for s in (100, 200, 400, 800, 1600)],
    "newton-xpbd": [{"substeps": s, "iterations": 2} for s in (10, 40, 160)],
    "newton-semi": [{"substeps": s} for s in (50, 100, 150, 200, 300, 400, 800, 1600)],
    "pbat-vbd": [{"substeps": s, "iterations": 1} for s in (100, 200, 400, 800, 1600)],
}


# --------------------------------------------------------------------------- scenes


def beam_reference() -> float:
    """Euler-Bernoulli plus Timoshenko shear tip deflection of the beam under its weight (m)."""
    b = BEAM
    area, inertia = b["width"] ** 2, b["width"] ** 4 / 12.0
    q = b["density"] * b["g"] * area
    shear = b["young"] / (2.0 * (1.0 + b["poisson"]))
    bending = q * b["length"] ** 4 / (8.0 * b["young"] * inertia)
    return bending + q * b["length"] ** 2 / (2.0 * 5.0 / 6.0 * shear * area)


def beam_problem(tets: int) -> Problem:
    import warpblob as wb

    b = BEAM
    ratio = b["length"] / b["width"]
    n = max(1, round((tets / 6.0 / ratio) ** (1.0 / 3.0)))  # cells across: 6 ratio n^3 tets
    cells = (round(n * ratio), n, n)
    mesh = wb.mesh.box_tetmesh((0.0, 0.0, 0.0), (b["length"], b["width"], b["width"]), cells)
    nodes = mesh.nodes.astype(np.float64)
    x = nodes[:, 0]
    return Problem("beam", nodes, np.asarray(mesh.tets), x <= 1e-9, x >= b["length"] - 1e-9, b["young"],
                   b["poisson"], b["density"], (0.0, 0.0, -b["g"]), FRAME_DT, {"cells": list(cells)})  # fmt: skip


def tumor_problem(tets: int) -> Problem:
    import warpblob as wb

    model = wb.scenes.tumor()
    h = 0.2
    # tets ~ h^-3: one calibration mesh, then the cellsize for the wanted count
    h *= (wb.tetrahedralize(model, cellsize=h).tet_count / tets) ** (1.0 / 3.0)
    mesh = wb.tetrahedralize(model, cellsize=h)
    nodes = mesh.nodes.astype(np.float64)
    x = nodes[:, 0]
    lo, hi = x.min(), x.max()
    t = TUMOR
    fixed, probe = x <= lo + t["fixed"] * (hi - lo), x >= hi - t["probe"] * (hi - lo)
    return Problem("tumor", nodes, np.asarray(mesh.tets), fixed, probe, t["young"], t["poisson"], t["density"],
                   (0.0, 0.0, -9.81), FRAME_DT, {"cellsize": h})  # fmt: skip


SCENES = {"beam": beam_problem, "tumor": tumor_problem}


def static_deflection(p: Problem, direct_max: int) -> tuple[float, str]:
    """Mean z displacement of the probe nodes at static equilibrium, linear FEM on ``p``'s mesh (scipy).

    Lumped gravity loads, the fixed nodes clamped. A sparse direct solve up to
    ``direct_max`` tets, else CG with a Jacobi preconditioner to 1e-10.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    mu, lam = p.lame
    x = p.nodes[p.tets]
    dm = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)
    inv = np.linalg.inv(dm)
    vol = np.linalg.det(dm) / 6.0
    grad = np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)  # (T, 4, 3) shape-function gradients
    dots = np.einsum("tai,tbi->tab", grad, grad)
    ke = lam * np.einsum("tai,tbj->taibj", grad, grad) + mu * np.einsum("taj,tbi->taibj", grad, grad)
    ke += mu * np.einsum("tab,ij->taibj", dots, np.eye(3))
    ke *= vol[:, None, None, None, None]
    dof = (p.tets[:, :, None] * 3 + np.arange(3)).reshape(-1, 12)
    n = 3 * p.node_count
    rows, cols = np.repeat(dof, 12, axis=1).ravel(), np.tile(dof, (1, 12)).ravel()
    k = sp.csr_matrix((ke.reshape(-1), (rows, cols)), shape=(n, n))
    mass = np.zeros(p.node_count)
    np.add.at(mass, p.tets.ravel(), np.repeat(p.density * vol / 4.0, 4))
    f = (mass[:, None] * np.asarray(p.gravity)[None, :]).ravel()
    free = np.repeat(~p.fixed, 3)
    kf = k[free][:, free]
    u = np.zeros(n)
    if p.tet_count <= direct_max:
        u[free], how = sla.spsolve(kf.tocsc(), f[free]), "direct"
    else:
        diag = kf.diagonal()
        pre = sla.LinearOperator(kf.shape, matvec=lambda r: r / diag)
        u[free], info = sla.cg(kf, f[free], rtol=1e-10, maxiter=200_000, M=pre)
        how = "cg" if info == 0 else f"cg (not converged, info {info})"
    return float(-u.reshape(-1, 3)[p.probe, 2].mean()), how


# --------------------------------------------------------------------------- one solver run (a child process)


def worker(spec: dict) -> dict:
    """Build one solver on the saved problem, time frames, then run it to rest; a JSON-able result."""
    threads = int(spec["threads"])
    if spec.get("pin") and hasattr(os, "sched_setaffinity"):
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, set(cpus[: max(1, threads)]))
    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = 40
    data = np.load(spec["problem"], allow_pickle=False)
    p = Problem(str(data["name"]), data["nodes"], data["tets"], data["fixed"], data["probe"],
                float(data["young"]), float(data["poisson"]), float(data["density"]), tuple(data["gravity"]),
                float(data["frame_dt"]))  # fmt: skip
    cls = ADAPTERS[spec["solver"]]
    setting = dict(spec["setting"])
    if spec["solver"] == "warpblob":
        setting["threads"] = threads
    out = {"solver": spec["solver"], "setting": spec["setting"], "threads": threads}
    try:
        solver = cls(p, **setting)
    except ImportError as err:
        return {**out, "skipped": str(err)}
    out["build_s"] = solver.build_s
    z0 = p.nodes[p.probe, 2].mean()
    extent = float(np.ptp(p.nodes, axis=0).max())
    drag = math.exp(-DRAG * p.frame_dt)
    ref = float(spec["reference"])
    frames, stages, deflection = [], [], []

    def advance(timed: bool):
        t0 = time.perf_counter()
        solver.frame()
        seconds = time.perf_counter() - t0
        if timed:
            frames.append(seconds)
            stages.append(solver.stages())
        solver.scale_velocity(drag)
        q = solver.positions()
        deflection.append(float(z0 - q[p.probe, 2].mean()))
        if not np.isfinite(q).all() or np.abs(q - p.nodes).max() > 2.0 * extent:
            raise FloatingPointError(f"blew up at frame {len(deflection)}: a node is not finite or moved > 2x the size")
        return seconds

    try:
        advance(False)  # compilation, first touch
        slow = advance(False) > spec["slow_frame_s"]
        for _ in range(2 if slow else int(spec["repeat"])):
            advance(True)
        order = np.argsort(frames)
        median = int(order[len(order) // 2])
        out.update(ms=1e3 * frames[median], ms_best=1e3 * frames[order[0]], timed_frames=len(frames))
        if stages[median]:
            st = stages[median]
            out["stages_ms"] = {k: 1e3 * v for k, v in st.get("seconds", {}).items()}
            out["cg_iterations"] = st.get("cg_iterations")
            out["residual"] = st.get("residual")
            out["coarse_size"] = st.get("coarse_size")
        if spec["accuracy"]:
            still, t0 = 0, time.perf_counter()
            while len(deflection) < spec["frames"] and time.perf_counter() - t0 < spec["budget_s"]:
                advance(False)
                speed = abs(deflection[-1] - deflection[-2]) / p.frame_dt
                still = still + 1 if speed < REST_SPEED * ref else 0
                if still >= 5 and len(deflection) >= 30:
                    break
            out.update(deflection=deflection[-1], tip_speed=abs(deflection[-1] - deflection[-2]) / p.frame_dt,
                       frames_run=len(deflection), at_rest=still >= 5,
                       out_of_time=time.perf_counter() - t0 >= spec["budget_s"])  # fmt: skip
        out["stable"] = True
    except Exception as err:  # noqa: BLE001 - a blow-up, whatever the solver raises, is a result
        out.update(stable=False, error=f"{type(err).__name__}: {err}"[:300], frames_run=len(deflection))
        if frames:
            out.setdefault("ms", 1e3 * float(np.median(frames)))
    out["settings"] = solver.describe()
    return out


def launch(spec: dict, timeout_s: float) -> dict:
    """Run :func:`worker` in a fresh process (isolates crashes, thread pools and CPU affinity)."""
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", json.dumps(spec)]
    env = dict(os.environ, WARPBLOB_THREADS=str(spec["threads"]))
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired:
        return {"solver": spec["solver"], "setting": spec["setting"], "threads": spec["threads"], "stable": None,
                "error": f"timed out after {timeout_s:.0f} s"}  # fmt: skip
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"solver": spec["solver"], "setting": spec["setting"], "threads": spec["threads"], "stable": False,
            "error": f"process exited {proc.returncode}: {' | '.join(tail)}"[:300]}  # fmt: skip


# --------------------------------------------------------------------------- the benchmark


def setting_text(solver: str, s: dict) -> str:
    if solver == "warpblob":
        text = f"dt 1/60, tol {s['tolerance']:g}" if "tolerance" in s else "dt 1/60"
        return f"{text}, {s['preconditioner']}" if "preconditioner" in s else text
    parts = [f"{s.get('substeps', 1)} sub"]
    if "iterations" in s:
        parts.append(f"{s['iterations']} it")
    return " x ".join(parts)


def finish_row(row: dict, p: Problem, refs: dict, kind: str) -> dict:
    row.update(model=p.name, tets=p.tet_count, nodes=p.node_count, kind=kind)
    row["setting_text"] = setting_text(row["solver"], row.get("settings") or row["setting"])
    d = row.get("deflection")
    if d is not None:
        if refs.get("analytic"):
            row["err_ref"] = abs(d - refs["analytic"]) / refs["analytic"]
        if refs.get("mesh"):
            row["err_mesh"] = abs(d - refs["mesh"]) / refs["mesh"]
        row["deflection_mm"] = 1e3 * d
    return row


def scaled(setting: dict, factor: float) -> dict:
    """``setting`` with its substeps scaled by ``factor`` (rounded up): the CFL rule for a finer mesh."""
    out = dict(setting)
    if "substeps" in out and factor > 1.0:
        out["substeps"] = int(math.ceil(out["substeps"] * factor))
    return out


def peer_list(text: str, ap: argparse.ArgumentParser) -> list[str]:
    peers = []
    for name in (n for n in text.split(",") if n):
        for solver in GROUPS.get(name, [name]):
            if solver not in DEFAULTS:
                ap.error(f"--peers: unknown solver {solver!r}; known: {', '.join(GROUPS)}, {', '.join(DEFAULTS)}")
            module = "pbatoolkit" if solver.startswith("pbat") else "newton"
            if importlib.util.find_spec(module) is None:
                print(f"  {solver}: skipped ({module} is not installed)")
            elif solver not in peers:
                peers.append(solver)
    return peers


def prepare(model: str, size: int, scratch: str, direct_max: int):
    """The scene at about ``size`` tets, saved for the solver processes, and its references."""
    p = SCENES[model](size)
    path = os.path.join(scratch, f"{model}_{size}.npz")
    np.savez(path, name=p.name, nodes=p.nodes, tets=p.tets, fixed=p.fixed, probe=p.probe, young=p.young,
             poisson=p.poisson, density=p.density, gravity=np.asarray(p.gravity), frame_dt=p.frame_dt)  # fmt: skip
    t0 = time.perf_counter()
    mesh_ref, how = static_deflection(p, direct_max)
    refs = {"analytic": beam_reference() if model == "beam" else None, "mesh": mesh_ref, "mesh_solve": how,
            "mesh_solve_s": time.perf_counter() - t0, "tets": p.tet_count, "nodes": p.node_count,
            **p.extra}  # fmt: skip
    analytic = f", analytic {1e3 * refs['analytic']:.2f} mm" if refs["analytic"] else ""
    print(f"{model}, {p.tet_count} tets, {p.node_count} nodes: the mesh's static deflection "
          f"{1e3 * mesh_ref:.2f} mm ({how}){analytic}", flush=True)  # fmt: skip
    return p, path, refs


def bench_mesh(p, path, refs, args, peers, matched, ladders, first: bool, ladder_here: bool) -> list[dict]:
    """Every row of one mesh: warpblob at each thread count, each peer's default, ladder or matched setting.

    A peer's default setting is run to rest on the smallest mesh only (``first``); on the larger ones it is
    timed and checked for blow-ups over the timed frames.
    """
    rows = []
    ref = refs["analytic"] or refs["mesh"]
    threads_all = [int(t) for t in args.threads.split(",") if t]

    def run(solver, setting, threads, kind, accuracy=True):
        spec = {"problem": path, "solver": solver, "setting": setting, "threads": threads, "repeat": args.repeat,
                "frames": args.frames, "budget_s": args.budget, "accuracy": accuracy, "reference": ref,
                "slow_frame_s": 5.0, "pin": solver in DEFAULTS and ADAPTERS[solver].threaded}  # fmt: skip
        row = finish_row(launch(spec, args.timeout), p, refs, kind)
        rows.append(row)
        note = row.get("skipped") or row.get("error") or ""
        err = f", err mesh {row['err_mesh']:.2%}" if "err_mesh" in row else ""
        ms = f"{row['ms']:.1f} ms" if row.get("ms") is not None else "-"
        print(f"  {solver:12s} {row['setting_text']:14s} {threads}t: {ms}{err} {note}", flush=True)
        return row

    mine = {"preconditioner": args.preconditioner} if args.preconditioner else {}
    wb_rows = {th: run("warpblob", mine, th, "warpblob", accuracy=th == threads_all[0]) for th in threads_all}
    target = max(args.match, wb_rows[threads_all[0]].get("err_mesh") or 0.0)
    for solver in peers:
        threads = threads_all if ADAPTERS[solver].threaded else [1]
        for th in threads:
            run(solver, DEFAULTS[solver], th, "default", accuracy=first and th == threads[0])
        key = (p.name, solver)
        if ladder_here:
            matched[key] = None
            ladders.setdefault(f"{p.name}_{p.tet_count}", {})[solver] = climb = []
            for setting in LADDERS[solver]:
                row = run(solver, setting, threads[0], "ladder")
                climb.append({k: row.get(k) for k in ("setting", "ms", "deflection", "err_ref", "err_mesh", "at_rest",
                                                      "stable", "error")})  # fmt: skip
                if row.get("stable") and row.get("err_mesh") is not None and row["err_mesh"] <= target:
                    row["kind"] = "matched"
                    matched[key] = {"setting": setting, "err_mesh": row["err_mesh"], "target": target,
                                    "tets": p.tet_count}  # fmt: skip
                    for th in threads[1:]:
                        run(solver, setting, th, "matched", accuracy=False)
                    break
                if row.get("out_of_time"):
                    break  # the next rung costs more: it would not fit the budget either
        elif matched.get(key):
            setting = scaled(matched[key]["setting"], (p.tet_count / matched[key]["tets"]) ** (1.0 / 3.0))
            for th in threads:
                run(solver, setting, th, "matched", accuracy=th == threads[0])
    for row in rows:
        base = wb_rows.get(row["threads"]) or wb_rows[threads_all[0]]
        if row["solver"] != "warpblob" and row.get("ms") and base.get("ms"):
            row["x_warpblob"] = row["ms"] / base["ms"]
    return rows


def main(argv=None):
    if argv is None and len(sys.argv) > 2 and sys.argv[1] == "--worker":
        print("RESULT " + json.dumps(worker(json.loads(sys.argv[2]))), flush=True)
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", help="comma-separated: beam, tumor (default both)")
    ap.add_argument("--sizes", help="target tet counts, comma-separated (default 10000,50000,200000)")
    ap.add_argument("--peers", help=f"comma-separated: newton, pbat or single solvers ({', '.join(DEFAULTS)})")
    ap.add_argument("--threads", help="CPU thread counts, comma-separated (default 1,2)")
    ap.add_argument("--ladder-models", help="scenes whose smallest size gets the ladders (default beam,tumor)")
    ap.add_argument("--frames", type=int, help="most frames of an accuracy run (default 180 = 3 s)")
    ap.add_argument("--budget", type=float, help="seconds an accuracy run may take (default 300)")
    ap.add_argument("--match", type=float, help="equal-accuracy target for err mesh, at least warpblob's (0.02)")
    ap.add_argument("--timeout", type=float, help="seconds before a solver process is stopped (default 1800)")
    ap.add_argument("--direct-max", type=int, help="largest mesh (tets) for a direct static solve (60000)")
    ap.add_argument("--preconditioner", help="warpblob's Simulation(preconditioner=...): two_level or "
                    "block_jacobi (default: the Simulation's default)")  # fmt: skip
    ap.add_argument("--contact-sizes", help="tumor tet counts of the probe contact timing, '' for none "
                    "(default 10000,50000,200000)")  # fmt: skip
    full = {"models": "beam,tumor", "sizes": "10000,50000,200000", "peers": "newton,pbat", "threads": "1,2",
            "ladder_models": "beam,tumor", "frames": 180, "budget": 300.0, "match": 0.02, "timeout": 1800.0,
            "direct_max": 60_000, "repeat": 5, "contact_sizes": "10000,50000,200000", "preconditioner": ""}  # fmt: skip
    quick = {**full, "sizes": "2000", "ladder_models": "beam", "frames": 120, "budget": 8.0, "timeout": 300.0,
             "repeat": 3, "contact_sizes": "3000"}  # fmt: skip
    args = arguments(ap, full, quick, argv)
    sizes = sorted(int(s) for s in args.sizes.split(",") if s)
    models = [m for m in args.models.split(",") if m]
    for m in models:
        if m not in SCENES:
            ap.error(f"--models: unknown scene {m!r}; known: {', '.join(SCENES)}")
    bench = Run("fem", "FEM benchmark: milliseconds per 1/60 s frame, warpblob vs peers on the same meshes", args)
    print(f"frames: {TIMING_FEM}")
    ver = versions()
    print("versions: " + ", ".join(f"{k} {v}" for k, v in ver.items()))
    peers = peer_list(args.peers, ap)
    rows, references, ladders, matched = [], {}, {}, {}
    with tempfile.TemporaryDirectory(prefix="bench_fem_") as scratch:
        for model in models:
            for i, size in enumerate(sizes):
                p, path, refs = prepare(model, size, scratch, args.direct_max)
                references[f"{model}_{p.tet_count}"] = refs
                ladder_here = i == 0 and model in args.ladder_models.split(",")
                rows += bench_mesh(p, path, refs, args, peers, matched, ladders, i == 0, ladder_here)
    report(rows, matched)
    contact = contact_rows([int(c) for c in args.contact_sizes.split(",") if c], args.threads)
    goals = targets(rows)
    bench.finish(
        {
            "timing": TIMING_FEM,
            "versions": ver,
            "frame_dt": FRAME_DT,
            "drag_per_s": DRAG,
            "rest_speed": REST_SPEED,
            "beam": BEAM,
            "tumor": TUMOR,
            "defaults": DEFAULTS,
            "ladders_tried": LADDERS,
            "match": args.match,
            "frames": args.frames,
            "budget_s": args.budget,
            "references": references,
            "matched": {f"{m}_{s}": v for (m, s), v in matched.items()},
            "ladders": ladders,
            "targets": goals,
            "rows": rows,
            "contact": contact,
        }
    )


def contact_timing(tets: int, *, contact: str = "field", threads: int = 1, steps: int = 120, timed: int = 20) -> dict:
    """Contact ms per step of the probe on the tumor at about ``tets`` tets, by stage (medians of ``timed`` steps
    once the probe is in: tet location, field evaluation, force spreading), warm."""
    import statistics

    import warpblob as wb
    from warpblob.scenarios import probe_tumor

    h = 0.2 * (wb.tetrahedralize(wb.scenes.tumor(), cellsize=0.2).tet_count / tets) ** (1 / 3)
    sim = probe_tumor(h, steps, contact=contact, threads=threads)
    sim.step(int(0.7 * steps) - timed)
    stages = {"locate": [], "field": [], "spread": [], "total": [], "step": []}
    for _ in range(timed):
        sim.step()
        for k, sec in sim.stats["contact"]["seconds"].items():
            stages[k].append(1e3 * sec)
        stages["total"].append(1e3 * sim.stats["seconds"]["contact"])
        stages["step"].append(1e3 * sum(sim.stats["seconds"].values()))
    out = {f"{k}_ms": round(statistics.median(v), 3) for k, v in stages.items()}
    out.update(tets=sim.tet_count, contact=contact, threads=threads, samples=sim.stats["contact"]["samples"],
               penetrating=sim.stats["contact"]["penetrating"])  # fmt: skip
    return out


def contact_rows(sizes: list[int], threads_text: str) -> list[dict]:
    """The probe-on-tumor contact cost (issue 13's target: at most 2 ms per step at 50K tets), printed as a table."""
    if not sizes:
        return []
    rows = [
        contact_timing(n, contact=mode, threads=int(t))
        for n in sizes
        for mode in ("field", "nearest")
        for t in threads_text.split(",")
        if t
    ]
    print("\ncontact, probe on the tumor (warm, medians of 20 steps with the probe in), ms per step:")
    columns = [("tets", "tets", "d"), ("contact", "contact", "s"), ("threads", "thr", "d"),
               ("locate_ms", "locate", ".3f"), ("field_ms", "field", ".3f"), ("spread_ms", "spread", ".3f"),
               ("total_ms", "contact", ".3f"), ("step_ms", "whole step", ".2f")]  # fmt: skip
    print(table(rows, columns))
    return rows


def report(rows: list[dict], matched: dict) -> None:
    """Print the table, warpblob's stages and the equal-accuracy settings (the rows are left as they are)."""
    shown = [{**r, **{k: ("yes" if r[k] else "no") for k in ("at_rest", "stable") if isinstance(r.get(k), bool)}}
             for r in rows]  # fmt: skip
    print(table(shown, COLUMNS))
    stage_rows = [{**r, **{f"stage_{k}_ms": v for k, v in r["stages_ms"].items()}} for r in rows if r.get("stages_ms")]
    if stage_rows:
        names = list(stage_rows[0]["stages_ms"])
        cols = [("model", "model", "s"), ("tets", "tets", "d"), ("threads", "thr", "d"), ("ms", "ms/frame", ".1f")]
        cols += [(f"stage_{k}_ms", k, ".1f") for k in names] + [("cg_iterations", "cg it", "d")]
        cols += [("coarse_size", "coarse", "d")]
        print("warpblob by stage, ms of the median frame:")
        print(table(stage_rows, cols))
    for (model, solver), m in matched.items():
        if m:
            found = f"{setting_text(solver, m['setting'])}, err mesh {m['err_mesh']:.2%} <= {m['target']:.2%}"
        else:
            found = "did not reach the target on its ladder"
        print(f"equal accuracy, {model}: {solver} {found}")


def targets(rows: list[dict]) -> list[dict]:
    """Per beam mesh: warpblob's best frame (any thread count) against each peer's best matched frame.

    A peer whose ladder never reached the target is listed with its most accurate rung instead.
    """
    out = []
    beam = [r for r in rows if r.get("model") == "beam"]
    for tets in sorted({r["tets"] for r in beam}):
        here = [r for r in beam if r["tets"] == tets]
        wb = [r["ms"] for r in here if r["solver"] == "warpblob" and r.get("stable") and r.get("ms")]
        if not wb:
            continue
        near_10k = 5_000 <= tets <= 15_000
        entry = {"tets": tets, "warpblob_ms": min(wb), "target_ms": TARGET_MS if near_10k else None}
        for solver in sorted({r["solver"] for r in here} - {"warpblob"}):
            mine = [r for r in here if r["solver"] == solver and r.get("stable")]
            best = [r for r in mine if r["kind"] == "matched" and r.get("ms")]
            if not mine:
                entry[solver] = {"unstable": True}
            elif best:
                r = min(best, key=lambda r: r["ms"])
                err = next((c["err_mesh"] for c in best if c.get("err_mesh") is not None), None)
                entry[solver] = {"matched_ms": r["ms"], "threads": r["threads"], "setting": r["setting"],
                                 "err_mesh": err, "warpblob_faster": min(wb) < r["ms"]}  # fmt: skip
            else:
                tried = [r for r in mine if r.get("err_mesh") is not None and r["kind"] != "default"]
                if tried:
                    close = min(tried, key=lambda r: r["err_mesh"])
                    entry[solver] = {"unmatched_best_err_mesh": close["err_mesh"], "its_ms": close["ms"],
                                     "its_setting": close["setting"]}  # fmt: skip
        out.append(entry)
    for e in out:
        goal = ""
        if e["target_ms"]:
            goal = f" (target {e['target_ms']:g} ms: {'met' if e['warpblob_ms'] <= e['target_ms'] else 'not met'})"
        print(f"beam {e['tets']} tets: warpblob {e['warpblob_ms']:.1f} ms{goal}")
        for solver, v in e.items():
            if isinstance(v, dict) and "matched_ms" in v:
                verdict = "warpblob faster" if v["warpblob_faster"] else "peer faster"
                err = "error not measured" if v["err_mesh"] is None else f"err mesh {v['err_mesh']:.1%}"
                at = setting_text(solver, v["setting"])
                print(f"  {solver} matched at {at} ({err}): {v['matched_ms']:.1f} ms, {verdict}")
            elif isinstance(v, dict) and v.get("unstable"):
                print(f"  {solver}: blew up at every setting tried")
            elif isinstance(v, dict):
                print(f"  {solver}: not matched; closest {setting_text(solver, v['its_setting'])} "
                      f"err mesh {v['unmatched_best_err_mesh']:.1%} at {v['its_ms']:.1f} ms")  # fmt: skip
    return out


COLUMNS = [
    ("model", "model", "s"),
    ("tets", "tets", "d"),
    ("solver", "solver", "s"),
    ("kind", "kind", "s"),
    ("setting_text", "setting", "s"),
    ("threads", "thr", "d"),
    ("ms", "ms/frame", ".1f"),
    ("x_warpblob", "x wb", ".2f"),
    ("cg_iterations", "cg it", "d"),
    ("deflection_mm", "defl mm", ".2f"),
    ("err_ref", "err ref", ".1%"),
    ("err_mesh", "err mesh", ".1%"),
    ("at_rest", "rest", "s"),
    ("stable", "stable", "s"),
]


if __name__ == "__main__":
    main()
