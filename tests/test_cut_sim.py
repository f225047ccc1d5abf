"""Cutting a running simulation: element data follow the cut, a severed piece falls freely."""

import copy
import numpy as np
import pytest
import warp as wp

import warpblob as wb
from warpblob.cut import SweepSurface, cut
from warpblob.cut._sim import Cutter, apply_cut
from warpblob.mesh import TetStructure, box_tetmesh


def _beam_sim(**options):
    beam = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (10, 2, 2))
    s = TetStructure.from_tetmesh(beam)
    sim = wb.Simulation(s, young=1e6, poisson=0.3, density=1000.0, fixed=beam.nodes[:, 0] == 0.0, **options)
    return s, sim


def test_severed_piece_falls_freely_and_the_rest_holds():
    s, sim = _beam_sim()
    sim.step(2)
    s.set_positions(sim.positions)
    r = cut(s, SweepSurface.plane((0.63, 0.1, 0.1), (1, 0, 0.05), 2.0), collect=False)
    assert r.components == 2
    apply_cut(sim, r)
    assert sim.node_count == len(s.node_rest) and sim.tet_count == len(s.cell_nodes)
    assert np.isclose(sim.volume(), s.to_tetmesh().volume(), rtol=1e-5)
    labels = s.components()
    tets = np.asarray(s.cell_nodes)
    far = np.unique(tets[labels == labels[_far_cell(s)]])
    z0, t0 = sim.positions[far, 2].mean(), sim.time
    vz0 = np.average(sim.velocities[far, 2], weights=sim.masses[far])
    sim.step(30)
    t = sim.time - t0
    # free fall: the piece's centre of mass drops v0 t + g t^2 / 2 (backward Euler's lag: under 2 steps of g dt)
    com = np.average(sim.positions[far, 2], weights=sim.masses[far])
    com0 = z0
    expect = com0 + vz0 * t - 0.5 * 9.81 * t * t
    assert abs(com - expect) < 9.81 * t * 2 * sim.dt
    # the fixed piece stays a cantilever: its sag stays under twice the static deflection q L^4 / (8 E I) (dynamic
    # overshoot of a suddenly loaded beam) plus a margin
    near = np.unique(tets[labels == labels[_near_cell(s)]])
    length, side = 0.63, 0.2
    static = 1000.0 * 9.81 * side**2 * length**4 / (8 * 1e6 * side**4 / 12)
    assert -sim.positions[near, 2].min() < 2.5 * static


def _far_cell(s):
    c = np.asarray(s.node_rest)[np.asarray(s.cell_nodes)].mean(axis=1)[:, 0]
    return int(np.argmax(np.where(np.asarray(s.cell_alive), c, -np.inf)))


def _near_cell(s):
    c = np.asarray(s.node_rest)[np.asarray(s.cell_nodes)].mean(axis=1)[:, 0]
    return int(np.argmin(np.where(np.asarray(s.cell_alive), c, np.inf)))


def test_new_nodes_move_with_the_body():
    s, sim = _beam_sim(gravity=(0, 0, 0))
    x = sim.positions
    sim.velocities = np.column_stack([0.1 * x[:, 1], np.zeros(len(x)), 0.5 * x[:, 0]])  # linear in x: lerps are exact
    s.set_positions(sim.positions)
    r = cut(s, SweepSurface.plane((0.55, 0.1, 0.1), (0.3, 1, 0), 2.0), collect=False)
    apply_cut(sim, r)
    new = r.new_nodes
    a, b, w = r.node_sources[:, 0], r.node_sources[:, 1], r.node_weights[:, None]
    v, p = sim.velocities, sim.positions
    assert np.allclose(v[new], (1 - w) * v[a] + w * v[b], atol=1e-6)
    split = np.asarray(s.node_origin)[new] == 1
    assert split.any() and np.allclose(v[new][split, 2], 0.5 * p[new][split, 0], atol=1e-6)
    assert np.allclose(sim.positions[new], np.asarray(s.node_position)[new], atol=1e-6)


def test_apply_cut_refuses_compacted_results():
    s, sim = _beam_sim()
    r = cut(s, SweepSurface.plane((0.5, 0.1, 0.1), (1, 0, 0), 2.0), collect=True)
    with pytest.raises(wb.SimulationError, match="collect"):
        apply_cut(sim, r)


@pytest.mark.parametrize("mode", ["progressive", "on_release"])
def test_scalpel_stroke_cuts_as_it_moves(mode):
    s, sim = _beam_sim(gravity=(0, 0, 0))
    blade = wb.tools.Scalpel(0.6, 0.05)
    # a vertical blade drawn across the beam at x = 0.52, tip below it, edge up through it
    path = wb.tools.Path.line((0.52, -0.3, -0.2), (0.52, 0.5, -0.2), 0.2, align=True)
    cutter = Cutter(blade, path, mode=mode)
    parts = []
    for _ in range(20):
        r = cutter.step(sim, sim.time, sim.time + sim.dt)
        parts.append(r is not None)
        sim.step()
    assert cutter.results and cutter.results[-1].components == 2
    if mode == "on_release":
        assert sum(parts) == 1
    else:
        assert sum(parts) > 1
    tm = s.to_tetmesh()
    assert tm.volumes().min() > 0 and np.isclose(tm.volume(), 0.04, rtol=1e-5)


def test_the_first_cutting_tool_warms_the_cutter_up_once_on_a_structure_of_its_own(monkeypatch, device):
    """add_tool(cut=True) runs the cutter's path once per device (warm_up: two progressive cuts and their
    rebuilds on its own 48-tet box); the simulation it was called on is untouched, and a second tool or a
    second call does not run it again."""
    import warpblob.cut._sim as cut_sim

    monkeypatch.setattr(cut_sim, "_WARMED", set())
    runs = []
    real_cut = cut_sim.cut

    def counted(structure, sweep, **kw):
        result = real_cut(structure, sweep, **kw)
        runs.append((structure, result))
        return result

    monkeypatch.setattr(cut_sim, "cut", counted)
    beam = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (10, 2, 2))
    s = TetStructure.from_tetmesh(beam)
    sim = wb.Simulation(s, young=1e6, poisson=0.3, density=1000.0, device=device)
    before = (len(s.cell_nodes), len(s.node_rest), sim.tet_count, sim.node_count, sim.positions.copy())
    path = wb.tools.Path.line((0.52, -0.3, -0.2), (0.52, 0.5, -0.2), 0.2, align=True)
    sim.add_tool(wb.tools.Scalpel(0.6, 0.05), path, cut=True)
    assert len(runs) == 2 and all(structure is not s for structure, _ in runs)
    # the first cut stops inside the box (progressive records), the second continues through them
    assert {"C", "D", "E"} & set(runs[0][1].tets_split) and runs[1][1].tets_split
    assert (len(s.cell_nodes), len(s.node_rest), sim.tet_count, sim.node_count) == before[:4]
    np.testing.assert_array_equal(sim.positions, before[4])
    sim.add_tool(wb.tools.Scalpel(0.6, 0.05), path, cut=True)
    assert len(runs) == 2 and not cut_sim.warm_up(device)


def test_simulation_scalpel_cuts_while_stepping_and_records(tmp_path):
    beam = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (10, 2, 2))
    s = TetStructure.from_tetmesh(beam)
    sim = wb.Simulation(s, young=1e6, poisson=0.3, density=1000.0, fixed=beam.nodes[:, 0] == 0.0)
    blade = wb.tools.Scalpel(0.6, 0.05)
    path = wb.tools.Path.line((0.52, -0.3, -0.2), (0.52, 0.5, -0.2), 0.2, align=True)
    cutter = sim.add_tool(blade, path, cut=True)
    assert sim.cutters == (cutter,)
    with wb.usd.Recorder(tmp_path / "cut.usdc") as rec:
        rec.add(sim)
        for _ in range(40):
            sim.step()
            rec.frame()
    assert cutter.results[-1].components == 2 and sim.stats["cut"]["components"] == 2
    tip = sim.positions[np.asarray(s.node_rest)[:, 0] > 0.99]
    assert tip[:, 2].max() < -0.5 * 9.81 * (sim.time - 0.2) ** 2 * 0.8  # the severed end falls freely
    tet = wb.usd.load_tetmesh(tmp_path / "cut.usdc", time=39)
    assert tet.tet_count == s.cell_count and tet.volumes().min() > 0
    with pytest.raises(wb.SimulationError, match="TetStructure"):
        wb.Simulation(beam, young=1e6, poisson=0.3, density=1000.0).add_tool(blade, path, cut=True)
    with pytest.raises(wb.ToolError, match="stiffness"):
        sim.add_tool(blade, path)
    with pytest.raises(wb.CutError, match="mode"):
        sim.add_tool(blade, path, cut=True, mode="sometimes")


def _cut_simulation():
    """A stepped simulation of a box (moved off rest, a heavier material in one half), cut by a stroke."""
    box = box_tetmesh((0, 0, 0), (1.0, 0.5, 0.5), (8, 4, 4))
    material = (box.nodes[box.tets].mean(axis=1)[:, 0] > 0.5).astype(np.int32)
    s = TetStructure.from_tetmesh(wb.TetMesh(box.nodes, box.tets, material=material))
    sim = wb.Simulation(s, young={0: 1e5, 1: 4e5}, poisson=0.35, density=1000.0, fixed=box.nodes[:, 0] == 0.0)
    sim.step(3)
    s.set_positions(sim.positions)
    a = np.array([[0.1, 0.23, 0.7], [0.8, 0.26, 0.7]])
    r = cut(s, SweepSurface.from_blade(a, a - (0, 0, 0.45)), collect=False)
    sim.apply_cut(r)
    return sim, r


def test_the_rows_a_rebuild_keeps_are_written_before_they_are_read():
    """A rebuild after a cut keeps, without clearing them, the old rows of the buffers that a step writes at
    every node before reading (the solver's system, CG vectors and filter; the other position and velocity
    buffers; the moved flags): poisoned with NaN there, the next steps of a simulation on the ground give the
    same positions, velocities and stats, bit for bit, as the same simulation not poisoned; the ones that must
    be zero after a rebuild (the contact arrays) are. (The coarse space's modes are carried over a cut with its
    factor, not written again: test_a_followed_coarse_space_keeps_its_factor_until_its_refresh.)"""
    from warpblob.sim._solver import _WRITTEN

    def made():
        sim, _ = _cut_simulation()
        sim.ground = (-0.05, 0.5)
        return sim

    clean, poisoned = made(), made()
    old = poisoned._solver.coarse.node_aggregate.shape[0] - 1  # (every row but the last: old nodes)
    assert poisoned._solver.coarse.followed
    victims = [getattr(poisoned._solver, name) for name in _WRITTEN if name != "ones"]
    victims += [poisoned._x[1], poisoned._v[1], poisoned._moved]
    for arr in victims:
        arr.numpy()[:old] = np.nan
    for sim in (clean, poisoned):
        for name in ("contact_force", "contact_weight", "contact_block"):
            assert not getattr(sim._solver, name).numpy().any()
        sim.step(3)
    np.testing.assert_array_equal(poisoned.positions, clean.positions)
    np.testing.assert_array_equal(poisoned.velocities, clean.velocities)
    assert poisoned.stats["cg_iterations_total"] == clean.stats["cg_iterations_total"]
    assert np.isfinite(clean.positions).all() and np.abs(clean.velocities).max() > 0


def test_a_followed_coarse_space_keeps_its_factor_until_its_refresh(monkeypatch):
    """A cut's rebuild keeps the factor of the coarse space it follows (CoarseSpace.carry_modes): each added
    node takes its source's mode offset and reference filter, the next step refreshes nothing (where a new
    solver's first step refreshed it: about a step's cost at 100K tets) and its CG still stops at its
    tolerance, not at the iteration cap, and
    its positions agree with those of the same step after a refresh to 1e-3 of the step's motion; the factor
    is refreshed on the solver's schedule, within COARSE_EVERY steps."""
    from warpblob.sim import _solver

    sim, r = _cut_simulation()
    c = sim._solver.coarse
    assert c.followed and c.modes_kept
    src = np.where(r.node_weights < 0.5, r.node_sources[:, 0], r.node_sources[:, 1])
    for rows in (c.node_mode.numpy(), c.reference.numpy()):
        np.testing.assert_array_equal(rows[r.new_nodes], rows[src])
    twin, _ = _cut_simulation()
    twin._solver.invalidate()  # (the step refreshes the factor, as every rebuild's first step did)
    x0 = sim.positions
    for run in (sim, twin):
        run.step(1)
        assert 0 < run.stats["cg_iterations"] < run.max_iterations  # (stopped by its tolerance, not the cap)
    assert sim.stats["coarse_refreshes"] == 0 and twin.stats["coarse_refreshes"] == 1
    motion = np.abs(twin.positions - x0).max()
    assert motion > 0 and np.abs(sim.positions - twin.positions).max() <= 1e-3 * motion
    refreshes = []
    for _ in range(_solver.COARSE_EVERY):
        sim.step(1)
        refreshes.append(sim.stats["coarse_refreshes"])
    assert refreshes[-1] >= 1, refreshes


def _box_with_probe(cells, path=None):
    """A box (1 x 0.5 x 0.5) on a TetStructure, simulated held at its floor without gravity, with a probe of
    stiffness 1e6 on ``path`` (default: from above its middle, down)."""
    from warpblob.tools import Path, Probe

    box = box_tetmesh((0, 0, 0), (1.0, 0.5, 0.5), cells)
    s = TetStructure.from_tetmesh(box)
    sim = wb.Simulation(s, young=1e5, poisson=0.35, density=1000.0, fixed=box.nodes[:, 2] == 0.0,
                        gravity=(0, 0, 0), model=wb.Box((0, 0, 0), (1.0, 0.5, 0.5), 0.05))  # fmt: skip
    path = Path.line((0.5, 0.25, 0.7), (0.5, 0.25, 0.6), 0.05) if path is None else path
    sim.add_tool(Probe(0.1), path, stiffness=1e6, kring=2)
    return box, s, sim


def test_a_rebuild_clears_the_contact_arrays_a_contact_pass_wrote():
    """The contact arrays are zero after a rebuild, as a new solver's are: cleared whole when a contact pass
    wrote them since they were last cleared, else only their added rows set (``contact_zero`` says which)."""
    from warpblob.tools import Path

    # pressed in by the third step, held, then away by the sixth
    keys, z = [0.0, 0.05, 0.07, 0.09], [0.52, 0.45, 0.45, 2.0]
    _, s, sim = _box_with_probe((16, 8, 8), Path(keys, [(0.5, 0.25, h) for h in z]))
    assert sim._solver.contact_zero
    blade = np.array([[0.05, 0.22, 0.7], [0.15, 0.22, 0.7]])
    for touching in (True, False):
        sim.step(3)
        contact = sim._solver.contact_weight.numpy()
        assert (contact > 0).any() == touching and sim._solver.contact_zero == (not touching)
        s.set_positions(sim.positions)
        r = cut(s, SweepSurface.from_blade(blade, blade - (0, 0, 0.3)), collect=False)
        assert len(r.new_nodes) > 0
        base = sim._solver._bases["contact_weight"]
        sim.apply_cut(r)
        assert sim._solver._bases["contact_weight"] is base  # (kept: not a fresh one)
        assert sim._solver.contact_zero
        for name in ("contact_force", "contact_weight", "contact_block"):
            assert not getattr(sim._solver, name).numpy().any()
        blade = blade + (0, 0.125, 0)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_the_ring_spread_follows_cuts_bit_for_bit(k):
    """The contact's k-ring spread followed over a cut's rebuild (ring_spread_after: the rows within 2 k of the
    changed tets' corners found again, those within 2 k weighed again, the rest copied) equals the spread made
    anew, offsets, nodes, weights, sums and rings bit for bit, over five random strokes (new nodes, dead tets,
    pieces coming apart), from the packed incidence and from its lists as the elements keep them, and with
    too little room for the rows searched again (written a second time at their places)."""
    from warpblob.sim._contact import _ring_spread, ring_spread_after

    box = box_tetmesh((0, 0, 0), (1.0, 0.5, 0.5), (10, 5, 5))
    s = TetStructure.from_tetmesh(box)
    sim = wb.Simulation(s, young=1e5, poisson=0.35, density=1000.0, fixed=box.nodes[:, 0] == 0.0)
    e = sim.elements
    rng = np.random.default_rng(k)
    for _ in range(5):
        before = _ring_spread(e.tets_host, e.alive_host & (e.volume.numpy() > 0), e.node_count, k)
        a = np.array([rng.uniform(0.05, 0.6), rng.uniform(0.05, 0.45), 0.7])
        blade = np.stack([a, a + (rng.uniform(0.1, 0.4), rng.uniform(-0.1, 0.1), 0.0)])
        r = cut(s, SweepSurface.from_blade(blade, blade - (0, 0, rng.uniform(0.2, 0.7))), collect=False)
        sim.apply_cut(r)
        live = e.alive_host & (e.volume.numpy() > 0)
        fresh = _ring_spread(e.tets_host, live, e.node_count, k)
        # (packed, and the lists where they are kept; with the rows' room too small for them, written again)
        for incidence, hint in ((e.incidence(), None), (e.incidence_lists(), None), (e.incidence_lists(), 2)):
            start = copy.deepcopy(before)  # (a follow edits the spread in place: each from its own copy)
            start.search.row_hint = hint or start.search.row_hint
            followed = ring_spread_after(start, e.tets_host, live, e.node_count, k, e.touched_nodes, incidence)
            assert len(followed.packed()) == len(fresh.packed()) == 5
            for a_, b_ in zip(fresh.packed(), followed.packed()):
                assert a_.dtype == b_.dtype
                np.testing.assert_array_equal(a_, b_)
    assert e.node_count > len(box.nodes)


def test_a_contact_follows_a_cut_and_binds_anew_after_any_other_edit():
    """A simulation with a contact tool: after a cut's rebuild the contact's spread is followed from the one
    before (and equals one made anew); after a rebuild of every tet it is made anew (the same spread)."""
    from warpblob.sim._contact import _ring_spread

    _, s, sim = _box_with_probe((8, 4, 4))
    contact = sim._contact
    blade = np.array([[0.05, 0.19, 0.7], [0.3, 0.19, 0.7]])
    r = cut(s, SweepSurface.from_blade(blade, blade - (0, 0, 0.3)), collect=False)
    sim.apply_cut(r)
    assert contact._follow is not None and 2 in contact._rings_before
    e = sim.elements
    fresh = _ring_spread(e.tets_host, e.alive_host & (e.volume.numpy() > 0), e.node_count, 2)
    for a_, b_ in zip(fresh.packed(), contact._rings[2].packed()):
        np.testing.assert_array_equal(a_, b_)
    sim.rebuild()  # (every tet: every node touched)
    for a_, b_ in zip(fresh.packed(), contact._rings[2].packed()):
        np.testing.assert_array_equal(a_, b_)


def test_a_contact_follows_random_cuts_as_a_new_bind_would_make_it():
    """Five random strokes through a simulation with a contact tool: after each rebuild the contact's
    boundary flags, boundary layer, median edge (and the sorted edge lengths it is taken from) and k-ring
    spread, followed from the ones before, equal those a new bind makes (the surface faces of the live tets,
    the tets with a node on them, the median of their edges, the spread made anew)."""
    from warpblob.mesh import TetMesh
    from warpblob.sim._contact import _ring_spread

    box, s, sim = _box_with_probe((10, 5, 5))
    contact = sim._contact
    rng = np.random.default_rng(7)
    for _ in range(5):
        a = np.array([rng.uniform(0.05, 0.6), rng.uniform(0.05, 0.45), 0.7])
        blade = np.stack([a, a + (rng.uniform(0.1, 0.4), rng.uniform(-0.1, 0.1), 0.0)])
        r = cut(s, SweepSurface.from_blade(blade, blade - (0, 0, rng.uniform(0.2, 0.7))), collect=False)
        sim.apply_cut(r)
        assert contact._follow is not None
        e = sim.elements
        live = e.alive_host & (e.volume.numpy() > 0)
        t = e.tets_host[live]
        near = np.zeros(e.node_count, dtype=bool)
        near[TetMesh(e.rest_host, t).surface_faces().ravel()] = True
        np.testing.assert_array_equal(contact._near, near)
        np.testing.assert_array_equal(contact._layer, np.flatnonzero(live)[near[t].any(axis=1)])
        edges = e.rest_host[t[:, [1, 2, 3, 2, 3, 3]]] - e.rest_host[t[:, [0, 0, 0, 1, 1, 2]]]
        assert contact.edge == float(np.median(np.linalg.norm(edges, axis=2)))  # (the live tets' median edge)
        # (the lengths it keeps sorted to take it: a regular box's median hardly moves with a few of them)
        lengths = np.sort(np.linalg.norm(edges, axis=2), axis=None)
        np.testing.assert_array_equal(contact._sorted_lengths.sorted(), lengths)
        for a_, b_ in zip(_ring_spread(e.tets_host, live, e.node_count, 2).packed(), contact._rings[2].packed()):
            np.testing.assert_array_equal(a_, b_)
    assert e.node_count > len(box.nodes)


def test_a_contact_keeps_its_tet_tree_over_cuts_and_locates_as_a_new_one():
    """Over cuts the contact keeps the tree it locates points in (its main BVH refit, the slots of tets that
    left the boundary layer emptied, the tets that joined in a second small tree) instead of building one over
    the layer anew: points all over the box and round it land in the same tets with the same barycentric
    coordinates and rest points, bit for bit, as with one tree built anew over the layer."""
    _, s, sim = _box_with_probe((10, 5, 5))
    contact = sim._contact
    sim.step(4)  # (the probe touches: the contact has built its tree)
    assert contact._tet_bvh is not None
    rng = np.random.default_rng(11)
    points = rng.uniform((-0.05, -0.05, -0.05), (1.05, 0.55, 0.55), (4000, 3)).astype(np.float32)
    dev = contact.device
    n = len(points)
    kept = 0
    for k in range(3):
        a = np.array([[0.1 + 0.25 * k, 0.05, 0.7], [0.15 + 0.25 * k, 0.25, 0.7]])
        s.set_positions(sim.positions)
        tree = contact._tet_bvh
        sim.apply_cut(cut(s, SweepSurface.from_blade(a, a - (0, 0, 0.5)), collect=False))
        sim.step(1)
        kept += contact._tet_bvh is tree and len(contact._extra) > 0 and bool((contact._slots < 0).any())
        x = sim._x[sim._cur]
        found = []
        for located in (contact, copy.copy(contact)):
            if located is not contact:  # (one tree over the layer, as a bind anew makes it, on a copy)
                located._place_layer(contact._layer, contact._layer_mask, local=False)
                located._refit(x)
                assert len(located._extra) == 0 and (located._slots >= 0).all()
            out = [wp.empty(n, dtype=t, device=dev) for t in (wp.vec3, wp.vec3, wp.int32, wp.vec4)]
            located._locate(x, wp.zeros(n, dtype=wp.int32, device=dev), wp.array(points, dtype=wp.vec3, device=dev),
                            wp.array(np.array([[0, 0, 0, 0, 0, 0, 1]], np.float32), dtype=wp.transform, device=dev),
                            wp.zeros(1, dtype=wp.int32, device=dev), *out)  # fmt: skip
            found.append([o.numpy() for o in out])
        for a_, b_ in zip(*found):
            np.testing.assert_array_equal(a_, b_)
        assert (found[0][2] >= 0).sum() > n // 10  # (points inside the layer's tets, and round them)
    assert kept == 3


def test_element_pass_after_a_cut_is_the_full_pass():
    """After a cut the element pass is recomputed for the changed tets only, the others' carried over: every
    array equals a full pass at the same positions, bit for bit."""
    from warpblob.sim._elements import Elements
    from warpblob.sim._solver import ElementState

    sim, r = _cut_simulation()
    assert r.tets_added > 0
    e = sim.elements
    full = ElementState(e.tet_count, e.node_count, e.device)
    full.compute(e, sim._x[sim._cur], sim.threads)
    for name in ("rotated", "corner_force", "corner_block", "energy", "volume", "node_force", "node_block"):
        np.testing.assert_array_equal(getattr(sim._state, name).numpy(), getattr(full, name).numpy(), err_msg=name)
    # the element data rebuilt for the changed tets and touched nodes only equal those built from scratch
    assert e.touched_nodes is not None and 0 < len(e.touched_nodes) < e.node_count
    fresh = Elements(e.rest_host, e.tets_host, e.alive_host, e.young_host, e.poisson_host, e.density_host,
                     device=e.device)  # fmt: skip
    for name in ("dm_inv", "volume", "mu", "lam", "mass"):
        np.testing.assert_array_equal(getattr(e, name).numpy(), getattr(fresh, name).numpy(), err_msg=name)
    _assert_same_incidence(e, fresh)


@pytest.mark.parametrize("room", [None, 0.0])
def test_successive_cuts_keep_the_state_and_the_element_data(room, monkeypatch):
    """Three strokes, each applied to the stepped simulation (odd and even step counts: either of the double
    buffers current): after each the old nodes keep their positions, velocities, external forces and the
    fixed nodes their targets (the rebuilt buffers are the old ones where they have room; with no room kept,
    copies into new ones), the new nodes sit where the structure put them, move with the velocity of the
    points they were made at and carry no external force, and every element array equals one built from
    scratch, bit for bit (incidence merged, host arrays grown in place)."""
    from warpblob.sim._elements import Elements

    if room is not None:
        monkeypatch.setattr("warpblob._stages.ROOM", room)
    sim, _ = _cut_simulation()
    s = sim._structure
    sim.external_forces = np.tile([0.0, 0.0, 0.5], (sim.node_count, 1))
    for k, y in enumerate((0.12, 0.3, 0.4)):
        sim.step(k + 1)
        s.set_positions(sim.positions)
        x, v, target, external = sim.positions, sim.velocities, sim._target.numpy().copy(), sim.external_forces
        a = np.array([[0.05, y, 0.7], [0.95, y + 0.02, 0.7]])
        r = cut(s, SweepSurface.from_blade(a, a - (0, 0, 0.4 + 0.02 * k)), collect=False)
        sim.apply_cut(r)
        n = len(x)
        assert sim.node_count > n
        np.testing.assert_array_equal(sim.positions[:n], x)
        np.testing.assert_array_equal(sim.velocities[:n], v)
        np.testing.assert_array_equal(sim._target.numpy()[:n], target)
        np.testing.assert_array_equal(sim.external_forces[:n], external)
        np.testing.assert_array_equal(sim.positions[n:], np.asarray(s.node_position)[n : sim.node_count])
        np.testing.assert_array_equal(sim._target.numpy()[n:], sim.positions[n:])
        np.testing.assert_array_equal(sim.external_forces[n:], 0.0)
        ends, w = r.node_sources.astype(np.int64), r.node_weights.astype(np.float64)[:, None]
        expected = ((1.0 - w) * v[ends[:, 0]] + w * v[ends[:, 1]]).astype(np.float32)
        np.testing.assert_array_equal(sim.velocities[r.new_nodes.astype(np.int64)], expected)
        e = sim.elements
        fresh = Elements(e.rest_host, e.tets_host, e.alive_host, e.young_host, e.poisson_host, e.density_host,
                         device=e.device)  # fmt: skip
        for name in ("dm_inv", "volume", "mu", "lam", "density", "mass"):
            np.testing.assert_array_equal(getattr(e, name).numpy(), getattr(fresh, name).numpy(),
                                          err_msg=f"{name} after cut {k}")  # fmt: skip
        _assert_same_incidence(e, fresh, f"after cut {k}")
    sim.step(2)
    assert np.isfinite(sim.positions).all()


@pytest.mark.parametrize("tail", ["roomy", "none"])
def test_incidence_kept_over_rebuilds_is_the_sorted_one(device, tail, monkeypatch):
    """Rebuilds that kill tets, revive dead ones, append tets and nodes, one after another, each merging the
    touched nodes' lists into those in use (in their slots where they fit, else moved to the free tail, or
    all packed again by a sort where the tail is full): the incidence and the masses equal those of elements
    built from scratch, bit for bit, after every rebuild (and a rebuild of all tets sorts afresh to the
    same). With a roomy tail every kind of update is seen without a sort; with none, sorts."""
    import warpblob.sim._elements as elements
    from warpblob.sim._elements import Elements

    if tail == "none":
        monkeypatch.setattr(elements, "_TAIL_SHARE", 0.0)
        monkeypatch.setattr(elements, "_TAIL", 0)
    sorts = []
    sort = Elements._sort_incidence
    monkeypatch.setattr(Elements, "_sort_incidence", lambda self: (sorts.append(1), sort(self))[1])
    m = box_tetmesh((0, 0, 0), (1, 1, 1), (4, 4, 4))
    T = len(m.tets)
    e = Elements(m.nodes, m.tets, np.ones(T, bool), np.full(T, 1e3), np.full(T, 0.3), np.full(T, 1e3), device=device)
    rng = np.random.default_rng(3)
    kept = moved = 0
    for step in range(4):
        T, N = e.tet_count, e.node_count
        before = e.node_range.numpy().copy()
        del sorts[:]
        live, dead = np.flatnonzero(e.alive_host), np.flatnonzero(~e.alive_host)
        kill = rng.choice(live, 7, replace=False)
        revive = dead[: 3]
        # new tets: copies of killed ones on a new node placed where the old one was
        copies = e.tets_host[kill[:4]].copy()
        rest = np.concatenate([e.rest_host, e.rest_host[copies[:, 0]]])
        copies[:, 0] = N + np.arange(4)
        ids = np.concatenate([kill, revive, T + np.arange(4)])
        tets = np.concatenate([e.tets_host[kill], e.tets_host[revive], copies])
        alive = np.concatenate([np.zeros(7, bool), np.ones(len(revive), bool), np.ones(4, bool)])
        e.rebuild(ids, tets=tets, alive=alive, rest=rest, young=np.full(len(ids), 1e3),
                  poisson=np.full(len(ids), 0.3), density=np.full(len(ids), 1e3 + step))  # fmt: skip
        assert e.touched_nodes is not None
        if not sorts:  # the touched old nodes' lists: kept in their slots or moved past every old list
            after = e.node_range.numpy()[: len(before)]
            t = e.touched_nodes[e.touched_nodes < len(before)]
            grew = after[t, 1] - after[t, 0] != before[t, 1] - before[t, 0]
            kept += int(np.sum(grew & (after[t, 0] == before[t, 0])))
            moved += int(np.sum(after[t, 0] >= before[:, 1].max()))
        assert len(sorts) == (tail == "none")
        fresh = Elements(e.rest_host, e.tets_host, e.alive_host, e.young_host, e.poisson_host, e.density_host,
                         device=device)  # fmt: skip
        for name in ("mass", "volume"):
            np.testing.assert_array_equal(getattr(e, name).numpy(), getattr(fresh, name).numpy(),
                                          err_msg=f"{name} after rebuild {step}")  # fmt: skip
        _assert_same_incidence(e, fresh, f"after rebuild {step}")
    if tail == "roomy":
        assert kept > 0 and moved > 0, (kept, moved)
    e.rebuild()
    _assert_same_incidence(e, fresh, "after a rebuild of every tet")


def _assert_same_incidence(e, fresh, when: str = "") -> None:
    """``e``'s incidence lists equal ``fresh``'s (packed by a sort of every corner) node by node, and its
    lists, wherever they sit in the buffer, do not overlap (each node's slots are its own)."""
    for a, b, name in zip(e.incidence(), fresh.incidence(), ("offsets", "corners")):
        np.testing.assert_array_equal(a, b, err_msg=f"incidence {name} {when}")
    # an independent reference: numpy's stable argsort of every live corner by node
    live = np.flatnonzero(e.alive_host)
    nodes = e.tets_host[live].ravel()
    corners = (4 * live[:, None] + np.arange(4)).ravel()
    order = np.argsort(nodes, kind="stable")
    np.testing.assert_array_equal(e.incidence()[1], corners[order], err_msg=f"incidence against numpy {when}")
    r = e.node_range.numpy().astype(np.int64)
    used = r[r[:, 1] > r[:, 0]]
    used = used[np.argsort(used[:, 0])]
    assert np.all(used[1:, 0] >= used[:-1, 1]), f"two nodes' lists overlap {when}"
    assert used.size == 0 or used[-1, 1] <= e.node_corners.shape[0]


def _reference_layout(c, e) -> tuple:
    """numpy's per-tet slot layout of coarse space ``c`` on elements ``e``: per live tet (every corner in an
    aggregate) u^2 slots for its u distinct corner aggregates in order of first appearance, from its first
    slot; returns (corner aggregates (T, 4), live (T,), u (T,), slot (T, 4, 4))."""
    agg = c.node_aggregate.numpy().astype(np.int64)
    corner = agg[e.tets_host.astype(np.int64)]
    live = e.alive_host & (corner >= 0).all(axis=1)
    rep = np.argmax(corner[:, :, None] == corner[:, None, :], axis=2)
    new = rep == np.arange(4)
    group = np.take_along_axis(np.cumsum(new, axis=1) - 1, rep, axis=1)
    u = np.where(live, new.sum(axis=1), 0)
    start = c.slot_start.numpy()[:-1]
    slot = np.where(live[:, None, None], start[:, None, None] + group[:, :, None] * u[:, None, None]
                    + group[:, None, :], 0)  # fmt: skip
    return corner, live, u, slot


def _check_grouping(c, corner, live, slot) -> None:
    """Every slot is listed once in the grouping by pair (the aggregation's and the one of the slots added
    since), each pair's slots in ascending order over the two (the order of a fresh layout's sums), and each
    live tet's slot names its corners' pair."""
    total = c.slots.shape[0]
    P = len(c.pair_aggregates)
    offsets, extra_offsets = c.pair_offsets.numpy(), c.extra_offsets.numpy()
    base, extra = c.pair_slots.numpy()[: offsets[-1]], c.extra_slots.numpy()[: extra_offsets[-1]]
    listed = np.sort(np.concatenate([base, extra]))
    np.testing.assert_array_equal(listed, np.arange(total))
    pair_of_slot = np.concatenate([np.repeat(np.arange(P), np.diff(offsets)), np.repeat(np.arange(P), np.diff(extra_offsets))])
    for p in range(P):
        summed = np.concatenate([base[offsets[p] : offsets[p + 1]], extra[extra_offsets[p] : extra_offsets[p + 1]]])
        assert (np.diff(summed) > 0).all()
    code = np.empty(total, dtype=np.int64)
    code[np.concatenate([base, extra])] = pair_of_slot
    pa = c.pair_aggregates.numpy().astype(np.int64)
    t, a, b = np.nonzero(live[:, None, None] & np.ones((1, 4, 4), bool))
    np.testing.assert_array_equal(pa[code[slot[t, a, b]]], np.stack([corner[t, a], corner[t, b]], axis=1))


def test_coarse_slots_are_the_reference_layout():
    """A coarse space built on the cut elements: its per-tet slots (kernels) against a numpy construction of
    the layout (_reference_layout), dense (dead tets none), every slot naming its aggregate pair (the
    coupling kernel that sums into them is checked through the coarse matrix it assembles, against
    ``P^T A P``, in test_sim_solver.py)."""
    from warpblob.sim._coarse import CoarseSpace

    sim, _ = _cut_simulation()
    e = sim.elements
    c = CoarseSpace(e, sim._solver.coarse_axes)
    G = c.aggregate_count
    corner, live, u, slot = _reference_layout(c, e)
    # the kernels find a tet's slots from its first slot and its corners' groups (the layout above)
    np.testing.assert_array_equal(c.slot_start.numpy(), np.concatenate([[0], np.cumsum(u * u)]))
    _check_grouping(c, corner, live, slot)
    assert (~live).sum() > 0 and (u > 1).sum() > 0 and G > 1


def test_a_cut_carries_the_coarse_space_over(monkeypatch):
    """Cuts that sever nothing keep the coarse space's aggregates (CoarseSpace.follow): old nodes keep theirs,
    each new node takes its source's (a split point: the nearer end of its edge); the live tets' slots do not
    overlap and are grouped by their pairs; the coarse matrix and its factor equal, bit for bit, those of a
    coarse space laid out from scratch on the same aggregates; the next step converges. Two cuts one after
    the other: the second follows a space that was followed (its added slots grouped apart from the
    aggregation's, merged over both cuts)."""
    from warpblob.sim import _coarse
    from warpblob.sim._coarse import CoarseSpace

    monkeypatch.setattr(_coarse, "FOLLOW_GROWTH", 1.0)  # (this small box grows by more than the default share)
    box = box_tetmesh((0, 0, 0), (1.0, 0.5, 0.5), (8, 4, 4))
    s = TetStructure.from_tetmesh(box)
    sim = wb.Simulation(s, young=1e5, poisson=0.35, density=1000.0, fixed=box.nodes[:, 0] == 0.0)
    sim.step(2)
    for a in (np.array([[0.1, 0.23, 0.7], [0.8, 0.26, 0.7]]), np.array([[0.3, 0.1, 0.7], [0.35, 0.4, 0.7]])):
        before = sim._solver.coarse.node_aggregate.numpy().copy()
        s.set_positions(sim.positions)
        r = cut(s, SweepSurface.from_blade(a, a - (0, 0, 0.45)), collect=False)
        assert r.components == 1 and r.tets_added > 0 and len(r.new_nodes) > 0
        sim.apply_cut(r)
        c, e = sim._solver.coarse, sim.elements
        assert c.followed
        agg = c.node_aggregate.numpy()
        mass = e.mass.numpy()
        old = len(before)
        np.testing.assert_array_equal(agg[:old][mass[:old] > 0], before[mass[:old] > 0])
        assert (agg[:old][mass[:old] <= 0] == -1).all()
        src = np.where(r.node_weights < 0.5, r.node_sources[:, 0], r.node_sources[:, 1])
        np.testing.assert_array_equal(agg[r.new_nodes], before[src])
        corner, live, u, slot = _reference_layout(c, e)
        starts = c.slot_start.numpy()[:-1][live]
        order = np.argsort(starts)
        ends = (starts + (u * u)[live])[order]
        assert (ends[:-1] <= starts[order][1:]).all() and ends[-1] <= c.slots.shape[0]
        _check_grouping(c, corner, live, slot)
        # the coarse matrix on the same aggregates, laid out from scratch (dead tets without slots)
        ref = CoarseSpace.laid_out(e, sim._solver.coarse_axes, agg, c.aggregate_count, c.cell)
        assert ref.slots.shape[0] < c.slots.shape[0]
        sim.step(1)  # (its assembly writes the filter's axes the coarse matrix reads)
        assert sim.stats["relative_residual"] <= sim.tolerance * 1.0001
        x, rotated = sim._x[sim._cur], sim._state.rotated
        for space in (c, ref):
            space.refresh(x, rotated, 1.3, 0.02)
        np.testing.assert_array_equal(c.coarse.numpy(), ref.coarse.numpy())
        # the nodes grouped by aggregate (merged over the cut) as a fresh layout sorts them
        np.testing.assert_array_equal(c.aggregate_offsets.numpy(), ref.aggregate_offsets.numpy())
        np.testing.assert_array_equal(c.aggregate_nodes.numpy(), ref.aggregate_nodes.numpy())
        np.testing.assert_array_equal(c.lower.numpy(), ref.lower.numpy())
        assert np.abs(ref.coarse.numpy()).max() > 0
    assert c.extra_offsets.numpy()[-1] > 0  # (the slots of both cuts' tets, apart)


def test_the_coarse_space_follows_an_edit_that_leaves_old_nodes_without_mass(device):
    """An edit that kills every tet of a corner node (which then leaves its aggregate) and appends copies of
    other tets on new nodes: the followed space groups the nodes by aggregate and assembles the coarse matrix
    as a space laid out from scratch on the same aggregates does, bit for bit."""
    from warpblob.sim._coarse import CoarseSpace
    from warpblob.sim._elements import Elements
    from warpblob.sim._solver import ElementState

    device = wp.get_device(device)
    box = box_tetmesh((0, 0, 0), (1.0, 0.5, 0.5), (8, 4, 4))
    N, T = len(box.nodes), len(box.tets)
    e = Elements(box.nodes, box.tets, np.ones(T, bool), np.full(T, 1e5), np.full(T, 0.35), np.full(T, 1e3),
                 device=device)  # fmt: skip
    ones = lambda n: wp.array(np.ones((n, 3), np.float32), dtype=wp.vec3, device=device)
    c0 = CoarseSpace(e, ones(N), pieces=1)
    corner = int(np.argmax(box.nodes.sum(axis=1)))  # (the box's far corner)
    kill = np.flatnonzero((box.tets == corner).any(axis=1))
    other = np.setdiff1d(np.arange(T), kill)[:3]
    copies = box.tets[other].copy()
    copies[:, 0] = N + np.arange(3)  # (each on a new node at its first corner)
    ids = np.concatenate([kill, T + np.arange(3)])
    e.rebuild(ids, tets=np.concatenate([box.tets[kill], copies]),
              alive=np.concatenate([np.zeros(len(kill), bool), np.ones(3, bool)]),
              rest=np.concatenate([box.nodes, box.nodes[box.tets[other, 0]]]), young=np.full(len(ids), 1e5),
              poisson=np.full(len(ids), 0.35), density=np.full(len(ids), 1e3))  # fmt: skip
    axes = ones(N + 3)
    c = c0.follow(e, axes, box.tets[other, 0].astype(np.int64), 1)
    assert c is not None and c.followed
    agg = c.node_aggregate.numpy()
    assert agg[corner] == -1 and (agg[N:] >= 0).all()
    ref = CoarseSpace.laid_out(e, axes, agg, c.aggregate_count, c.cell)
    np.testing.assert_array_equal(c.aggregate_offsets.numpy(), ref.aggregate_offsets.numpy())
    np.testing.assert_array_equal(c.aggregate_nodes.numpy(), ref.aggregate_nodes.numpy())
    x = wp.array(e.rest_host * 1.01, dtype=wp.vec3, device=device)
    state = ElementState(e.tet_count, e.node_count, e.device)
    state.compute(e, x)
    for space in (c, ref):
        space.refresh(x, state.rotated, 1.3, 0.02)
    np.testing.assert_array_equal(c.coarse.numpy(), ref.coarse.numpy())
    assert np.abs(ref.coarse.numpy()).max() > 0


def test_the_box_of_the_nodes_with_mass_follows_edits():
    """The rest box of the nodes with mass (the scale of the solver's tolerances) kept over edits: five
    random strokes, then a rebuild that kills the slab of tets at x = 0 (its nodes there lose their mass and
    the box shrinks) and one that kills a tet inside (no node leaves the box's faces): after each it is the
    box of the nodes with mass taken anew."""
    box = box_tetmesh((0, 0, 0), (1.0, 0.5, 0.5), (10, 5, 5))
    s = TetStructure.from_tetmesh(box)
    sim = wb.Simulation(s, young=1e5, poisson=0.35, density=1000.0)
    rng = np.random.default_rng(11)

    def expected():
        rest = sim.elements.rest_host[sim._mass > 0]
        return rest.min(axis=0), rest.max(axis=0)

    edits = 0
    while edits < 5:
        a = np.array([rng.uniform(0.05, 0.6), rng.uniform(0.05, 0.45), 0.7])
        blade = np.stack([a, a + (rng.uniform(0.1, 0.4), rng.uniform(-0.1, 0.1), 0.0)])
        r = cut(s, SweepSurface.from_blade(blade, blade - (0, 0, rng.uniform(0.2, 0.7))), collect=False)
        sim.apply_cut(r)
        if not r.tets_added:  # (a stroke that only touched nodes: nothing rebuilt)
            continue
        edits += 1
        assert sim.elements.touched_nodes is not None  # (a local edit: the box followed)
        for got, want in zip(sim._bounds, expected()):
            np.testing.assert_array_equal(got, want)
    e = sim.elements
    centre = e.rest_host[e.tets_host].mean(axis=1)
    live = e.alive_host.copy()
    slab = np.flatnonzero(live & (centre[:, 0] < 0.1))
    inner = np.flatnonzero(live & (np.abs(centre - (0.5, 0.25, 0.25)).max(axis=1) < 0.06))[:1]
    for dead, shrinks in ((slab, True), (inner, False)):
        before = [b.copy() for b in sim._bounds]
        sim.rebuild(dead, alive=np.zeros(len(dead), dtype=bool))
        assert sim.elements.touched_nodes is not None
        for got, want in zip(sim._bounds, expected()):
            np.testing.assert_array_equal(got, want)
        assert (sim._bounds[0][0] > before[0][0]) == shrinks
    assert sim._bounds[0][0] >= 0.1 - 1e-6


@pytest.mark.parametrize("growth", [0.0, 1.0])
def test_the_coarse_space_is_made_anew_once_the_nodes_grew(growth, monkeypatch):
    """The aggregates are carried over cuts only while the nodes have grown by at most FOLLOW_GROWTH since
    they were made (then aggregated anew, on a lattice fitted to the nodes there are)."""
    from warpblob.sim import _coarse

    monkeypatch.setattr(_coarse, "FOLLOW_GROWTH", growth)
    box = box_tetmesh((0, 0, 0), (1.0, 0.5, 0.5), (8, 4, 4))
    s = TetStructure.from_tetmesh(box)
    sim = wb.Simulation(s, young=1e5, poisson=0.35, density=1000.0, fixed=box.nodes[:, 0] == 0.0)
    a = np.array([[0.1, 0.23, 0.7], [0.8, 0.26, 0.7]])
    r = cut(s, SweepSurface.from_blade(a, a - (0, 0, 0.45)), collect=False)
    assert r.components == 1 and len(r.new_nodes) > 0
    sim.apply_cut(r)
    assert sim._solver.coarse.followed == (growth > 0)


def test_rebuild_checks_the_new_nodes_data_before_changing_anything():
    """Bad ``new_sources`` (or velocities) for the nodes a cut added raise SimulationError naming the value,
    and the simulation is left as it was: the cut can then be applied."""
    box = box_tetmesh((0, 0, 0), (1.0, 0.5, 0.5), (4, 2, 2))
    s = TetStructure.from_tetmesh(box)
    sim = wb.Simulation(s, young=1e5, poisson=0.35, density=1000.0)
    r = cut(s, SweepSurface.plane((0.52, 0.25, 0.25), (1.0, 0.1, 0.0), 2.0), collect=False)
    T, N = sim.tet_count, sim.node_count
    added = len(s.node_rest) - N
    assert added > 0
    ids = np.concatenate([r.removed, r.added])
    with pytest.raises(wb.SimulationError, match=rf"new_sources must be \({added},\) ints in \[0, {N}\)"):
        sim.rebuild(ids, new_sources=np.full(added, N + 5))
    with pytest.raises(wb.SimulationError, match="new_velocities"):
        sim.rebuild(ids, new_velocities=np.zeros((added + 1, 3)))
    assert sim.tet_count == T and sim.node_count == N and sim.elements.tet_count == T
    sim.apply_cut(r)
    assert sim.tet_count == len(s.cell_nodes) and sim.node_count == len(s.node_rest)


def test_rebound_launches_step_as_freshly_recorded_ones(monkeypatch):
    """A rebuild after a cut rebinds the solver's recorded launches (new sizes, new arrays) instead of recording
    them anew: cuts with steps between (odd and even counts) give the same positions and CG iterations, bit
    for bit, as with every launch recorded afresh."""
    from warpblob.sim._solver import Prepared

    def run():
        sim, _ = _cut_simulation()
        s = sim._structure
        for k, y in enumerate((0.12, 0.3, 0.4)):
            sim.step(k + 1)
            s.set_positions(sim.positions)
            a = np.array([[0.05, y, 0.7], [0.95, y + 0.02, 0.7]])
            sim.apply_cut(cut(s, SweepSurface.from_blade(a, a - (0, 0, 0.4 + 0.02 * k)), collect=False))
        sim.step(3)
        return sim.positions, sim.velocities, sim.stats["cg_iterations_total"]

    rebind, rebound = Prepared.rebind, []
    monkeypatch.setattr(Prepared, "rebind", lambda self, *a: rebound.append(rebind(self, *a)) or rebound[-1])
    kept = run()
    assert sum(rebound) >= 3 * 13, rebound  # every launch of every rebuild's solver rebound
    monkeypatch.setattr(Prepared, "rebind", lambda self, *a: False)
    fresh = run()
    np.testing.assert_array_equal(kept[0], fresh[0])
    np.testing.assert_array_equal(kept[1], fresh[1])
    assert kept[2] == fresh[2] > 0


def test_the_energy_budget_follows_a_cut():
    """After a cut the step's energy budget (kinetic + elastic energy at the state) is updated from the changed
    tets and the nodes whose masses changed: it equals a full pass over every node and tet to rounding, over
    successive cuts of a moving, strained body."""
    sim, r = _cut_simulation()
    s = sim._structure

    def full():
        x, v = sim._x[sim._cur], sim._v[sim._cur]
        _, sums = sim._reduce(x, x, v, sim._state)
        return sums["kinetic"] + sums["elastic"]

    assert r.tets_added > 0 and sim.elements.touched_nodes is not None
    for k, y in enumerate((None, 0.3, 0.4)):
        if y is not None:
            sim.step(k + 1)
            s.set_positions(sim.positions)
            a = np.array([[0.05, y, 0.7], [0.95, y + 0.02, 0.7]])
            sim.apply_cut(cut(s, SweepSurface.from_blade(a, a - (0, 0, 0.4 + 0.02 * k)), collect=False))
        x, v = sim._x[sim._cur], sim._v[sim._cur]
        reference = full()
        kinetic = sim._reduce(x, x, v, sim._state)[1]["kinetic"]
        assert kinetic > 0.05 * reference > 0  # both parts count
        assert sim._budget == pytest.approx(reference, rel=1e-6), k
