"""Tool contact through the deformation-mapped field: idle tools change nothing, the force rises with depth and
the penetration stays small, the field map is right at rest and under rigid motion, determinism across thread
counts, the thesis' nearest-node variant, the k-ring spread against TetStructure's rings, the sample areas, a
very stiff contact at dt = 1/60, a rebuild, and the errors.
"""

import numpy as np
import pytest

import warpblob as wb
from warpblob import SimulationError, ToolError
from warpblob.mesh import TetStructure
from warpblob.sim import _contact
from warpblob.sim._contact import ring_spread, sample_areas
from warpblob.tools import Path, Probe, Tool

MODEL = wb.Box((0, 0, 0), (0.5, 0.5, 0.2), 0.3)


@pytest.fixture(scope="module")
def block():
    return wb.tetrahedralize(MODEL, cellsize=0.15)


def simulation(volume, **kw) -> wb.Simulation:
    z = volume.nodes[:, 2]
    options = dict(young=1e5, poisson=0.45, density=1000.0, gravity=(0, 0, 0), model=MODEL, fixed=z < z.min() + 0.05,
                   damping=(20.0, 0.0))  # fmt: skip
    options.update(kw)
    return wb.Simulation(volume, **options)


def top(volume) -> float:
    return float(volume.nodes[:, 2].max())


def test_a_tool_that_never_meets_the_tissue_changes_nothing(block):
    plain = simulation(block, gravity=(0, 0, -9.81))
    plain.step(20)
    touring = simulation(block, gravity=(0, 0, -9.81))
    # one skims the top, its box overlapping the tissue's (the whole contact pipeline runs), one stays far away
    touring.add_tool(Probe(0.4), Path.line((-0.3, 0, top(block) + 0.03), (0.3, 0, top(block) + 0.03), 0.3),
                     stiffness=1e7)  # fmt: skip
    touring.add_tool(Probe(0.4), Path.line((5, 5, 5), (6, 5, 5), 0.3), stiffness=1e7)
    touring.step(20)
    assert touring.stats["seconds_total"]["contact"] > 0 and touring.stats["contact"]["samples"] > 0
    assert plain.positions.tobytes() == touring.positions.tobytes()
    assert plain.velocities.tobytes() == touring.velocities.tobytes()
    assert not touring.contact_force().any() and len(touring.contact_points()) == 0
    assert len(touring.contact_nodes()) == 0


def test_the_force_rises_with_depth_and_the_penetration_stays_small(block):
    """A probe pressed into a held block in four stages, each held until the block settles.

    The contact law is the depth with its onset smoothed over a band of a tenth of the edge length; at this
    stiffness the load sinks the probe by less than another 0.15 edge, so the deepest sample stays within a
    quarter of an edge of the surface.
    """
    sim = simulation(block)
    depths = [0.02, 0.04, 0.06, 0.08]
    keys = [0.0]
    for _ in depths:
        keys += [keys[-1] + 0.1, keys[-1] + 0.4]
    positions = [(0, 0, top(block) + 0.02)] + [(0, 0, top(block) - d) for d in depths for _ in range(2)]
    sim.add_tool(Probe(0.5), Path(keys, positions), stiffness=1e7)
    settled = {round(t / sim.dt) for t in keys[2::2]}
    forces, deepest = [], []
    for i in range(1, max(settled) + 1):
        sim.step()
        if i in settled:
            force = sim.contact_force(0)
            assert force[2] > 0 and np.linalg.norm(force[:2]) < 0.05 * force[2]  # pushed straight back up
            forces.append(force[2])
            deepest.append(sim._contact.deepest[0])
            assert np.abs(sim.velocities).max() < 0.05  # settled: below 5% of the probe's speed while moving
    assert np.all(np.diff(forces) > 0)
    edge = sim.tools[0].spacing
    assert max(deepest) < 0.25 * edge
    points = sim.contact_points(0)
    assert len(points) > 0 and np.all(points[:, 2] < top(block) - depths[-1] + 0.25 * edge)


def test_the_mapped_field_is_the_rest_field_at_rest_and_moves_with_a_rigid_motion(block):
    sim = simulation(block)
    rng = np.random.default_rng(3)
    tets = block.tets[rng.choice(block.tet_count, 200, replace=False)]
    weights = rng.dirichlet(np.ones(4), 200)
    points = np.einsum("pk,pkd->pd", weights, block.nodes[tets].astype(np.float64))
    values, gradients, _ = wb.evaluate(MODEL, points)
    mapped, mapped_gradients = sim.field(points)
    np.testing.assert_allclose(mapped, values, atol=1e-5)
    np.testing.assert_allclose(mapped_gradients, gradients, atol=1e-4 * np.abs(gradients).max())

    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(1.1) * K + (1 - np.cos(1.1)) * K @ K
    shift = np.array([0.3, -0.2, 0.7])
    sim.positions = block.nodes @ R.T + shift
    mapped, mapped_gradients = sim.field(points @ R.T + shift)
    np.testing.assert_allclose(mapped, values, atol=1e-5)
    np.testing.assert_allclose(mapped_gradients, gradients @ R.T, atol=1e-4 * np.abs(gradients).max())
    outside, zero = sim.field(np.array([[10.0, 10.0, 10.0]]))
    assert outside[0] == 0 and not zero.any()


def pressed(volume, threads=None, contact="field", stiffness=1e7) -> wb.Simulation:
    sim = simulation(volume, threads=threads)
    sim.add_tool(Probe(0.4), Path.line((0.05, 0, top(volume) + 0.02), (0.1, 0.05, top(volume) - 0.08), 0.3),
                 stiffness=stiffness, contact=contact)  # fmt: skip
    sim.step(24)
    return sim


def test_contact_is_bit_identical_for_any_thread_count(block, monkeypatch):
    # small grains, so that every contact launch of this small mesh is split over the threads
    monkeypatch.setattr(_contact, "NODE_GRAIN", 16)
    monkeypatch.setattr(_contact, "_SAMPLE_GRAIN", 16)
    one, two = pressed(block, threads=1), pressed(block, threads=2)
    assert one.stats["contact"]["penetrating"] > 0
    assert one.positions.tobytes() == two.positions.tobytes()
    assert one.contact_force().tobytes() == two.contact_force().tobytes()


def test_the_nearest_node_variant_pushes_too(block):
    field, nearest = pressed(block), pressed(block, contact="nearest")
    for sim in (field, nearest):
        assert sim.contact_force(0)[2] > 0 and len(sim.contact_nodes()) > 0
    # the thesis reads the rest field: once pressed in, the whole sunk face counts as penetrating
    assert nearest.stats["contact"]["penetrating"] >= field.stats["contact"]["penetrating"]


def test_a_very_stiff_contact_is_stable_at_sixty_hertz(block):
    sim = pressed(block, stiffness=1e11)  # about 1e5 times the tissue's own stiffness under the probe
    assert np.isfinite(sim.energy()["total"])
    assert sim._contact.deepest[0] < 0.25 * sim.tools[0].spacing
    x = sim.positions
    assert np.all(np.einsum("ij,ij->i", np.cross(x[block.tets[:, 1]] - x[block.tets[:, 0]],
                                                 x[block.tets[:, 2]] - x[block.tets[:, 0]]),
                            x[block.tets[:, 3]] - x[block.tets[:, 0]]) > 0)  # fmt: skip


def test_the_spread_follows_the_structure_rings_and_keeps_the_force(block):
    """Every row of the k-ring spread (the kernel's search) is the node's rings by the structure's own
    ``k_ring``, each entry with its ring, for k = 1, 2, 3; the weights go 3 : 2 : 1 by ring and lose nothing."""
    from warpblob.sim._contact import _ring_spread

    structure = TetStructure.from_tetmesh(block)
    alive = np.ones(block.tet_count, bool)
    for k in (1, 2, 3):
        offsets, nodes, _, _, rings = _ring_spread(block.tets, alive, block.node_count, k).packed()
        for node in range(0, block.node_count, 1 if k < 3 else 7):
            row = slice(offsets[node], offsets[node + 1])
            within = [np.union1d(structure.k_ring(node, r), [node]) for r in range(k + 1)]
            assert np.array_equal(nodes[row], within[k])
            ring_of = [min(r for r in range(k + 1) if c in within[r]) for c in nodes[row]]
            np.testing.assert_array_equal(rings[row], ring_of)
    offsets, nodes, weights = ring_spread(block.tets, alive, block.node_count, 2)
    rows = np.repeat(np.arange(block.node_count), np.diff(offsets))
    for node in (0, 17, block.node_count // 2, block.node_count - 1):
        assert np.array_equal(nodes[offsets[node] : offsets[node + 1]], np.union1d(structure.k_ring(node, 2), [node]))
        # what ``node`` spreads: to itself, its first ring and its second, with weights 3 : 2 : 1
        column = nodes == node
        first = np.isin(rows[column], structure.k_ring(node, 1))
        ring = np.where(rows[column] == node, 0, np.where(first, 1, 2))
        for r in range(3):
            np.testing.assert_allclose(weights[column][ring == r] / weights[column][ring == 0], (3 - r) / 3, rtol=1e-6)
    # every node's force is spread without loss
    np.testing.assert_allclose(np.bincount(nodes, weights=weights, minlength=block.node_count), 1.0, rtol=1e-5)


def test_the_samples_share_the_tool_area():
    probe = Probe(0.5)
    for spacing in (0.5, 0.1, 0.03):
        samples = probe.sample_surface(spacing)
        area = sample_areas(probe, samples)
        assert np.all(area > 0)
        np.testing.assert_allclose(area.sum(), 6 * 0.25, rtol=1e-9)


def test_the_spread_rebuilds_with_the_elements(block):
    sim = pressed(block)
    before = sim.contact_force(0).copy()
    sim.rebuild()
    sim.step()
    assert sim.contact_force(0)[2] > 0 and abs(sim.contact_force(0)[2] - before[2]) < 0.2 * before[2]


def test_tool_errors_name_the_value(block):
    sim = simulation(block)
    probe, path = Probe(0.4), Path.line((0, 0, 1), (0, 0, 0), 1.0)
    for bad in (0.0, -5.0, float("nan"), "stiff"):
        with pytest.raises(ToolError, match=f"stiffness.*{bad}"):
            sim.add_tool(probe, path, stiffness=bad)
    with pytest.raises(ToolError, match="kring.*-1"):
        sim.add_tool(probe, path, stiffness=1.0, kring=-1)
    with pytest.raises(ToolError, match="'sideways'"):
        sim.add_tool(probe, path, stiffness=1.0, contact="sideways")
    with pytest.raises(ToolError, match="tool must be"):
        sim.add_tool(probe.vertices, path, stiffness=1.0)
    with pytest.raises(ToolError, match="path must be"):
        sim.add_tool(probe, [(0, 0, 0)], stiffness=1.0)
    with pytest.raises(ToolError, match=r"times\[1\] = 0.0"):
        sim.add_tool(probe, Path([0.0, 0.0], [(0, 0, 0), (0, 0, 1)]), stiffness=1.0)
    with pytest.raises(ToolError, match="nan"):
        sim.add_tool(probe, Path([0.0, 1.0], [(0, 0, 0), (0, float("nan"), 1)]), stiffness=1.0)
    with pytest.raises(ToolError, match=r"edge \(\d+, \d+\) of face \d+ runs 1 time"):  # a cube with a face missing
        sim.add_tool(Tool(probe.vertices, probe.faces[:-1]), path, stiffness=1.0)
    with pytest.raises(ToolError, match="tool must be an index"):
        sim.contact_force(3)
    assert not sim.tools


def test_field_contact_needs_the_model(block):
    sim = wb.Simulation(block, young=1e5, poisson=0.45, density=1000.0)
    with pytest.raises(SimulationError, match="model"):
        sim.add_tool(Probe(0.4), Path.line((0, 0, 1), (0, 0, 0), 1.0), stiffness=1.0)
    with pytest.raises(SimulationError, match="model"):
        sim.field([[0.0, 0.0, 0.0]])
    sim.add_tool(Probe(0.4), Path.line((0, 0, 1), (0, 0, 0), 1.0), stiffness=1.0, model=MODEL)
    with pytest.raises(SimulationError, match="already has a model"):
        sim.add_tool(Probe(0.4), Path.line((0, 0, 1), (0, 0, 0), 1.0), stiffness=1.0, model=wb.scenes.peanut())


def test_the_nodes_by_edge_distance_from_a_set_are_numpy_s(block):
    """The search a cut's follow starts from (``_levels``: the nodes within d edges of a set, level by level,
    over the live tets) against a breadth-first search in numpy over the live tets' edges, with a fifth of
    the tets dead, from one node and from a scattered set, to depth 4."""
    from warpblob.sim._contact import _levels, _RingSearch

    rng = np.random.default_rng(2)
    tets, N = block.tets.astype(np.int32), block.node_count
    alive = rng.random(len(tets)) > 0.2
    order = np.argsort(tets.ravel(), kind="stable").astype(np.int32)
    offsets = np.zeros(N + 1, dtype=np.int64)
    np.cumsum(np.bincount(tets.ravel(), minlength=N), out=offsets[1:])
    live = tets[alive]
    pairs = np.concatenate([live[:, [a, b]] for a in range(4) for b in range(4) if a != b])
    search = _RingSearch(0)
    for sources in (np.array([N // 2]), np.unique(rng.integers(0, N, 12))):
        found, ends = _levels(search, (offsets, order), tets, alive, sources.astype(np.int32), N, 4)
        seen = np.zeros(N, dtype=bool)
        seen[sources] = True
        level = sources
        for d in range(5):
            got = found[(ends[d - 1] if d else 0) : ends[d]]
            assert len(np.unique(got)) == len(got)
            np.testing.assert_array_equal(np.sort(got), np.sort(level))
            step = np.unique(pairs[np.isin(pairs[:, 0], level), 1])
            level = step[~seen[step]]
            seen[level] = True


def test_sorted_lengths_are_spliced_as_a_sort_anew_would_give_them():
    """The splice of a sorted multiset's pending values into its base (``_sorted_after``): against numpy's
    sort of the edited multiset, with many equal values, changes at both ends, nothing changed, and a value
    to take out that is not there (None: sorted anew)."""
    rng = np.random.default_rng(3)
    for trial in range(40):
        values = rng.integers(0, 12 if trial % 2 else 1000, 500).astype(np.float32) / 7
        ordered = np.sort(values)
        out = rng.choice(len(values), int(rng.integers(0, 40)) if trial else 0, replace=False)
        gone = values[out]
        came = rng.integers(-2, 14 if trial % 2 else 1010, int(rng.integers(0, 40)) if trial else 0)
        came = came.astype(np.float32) / 7
        expected = np.sort(np.concatenate([np.delete(values, out), came]))
        spliced = _contact._sorted_after(ordered, gone, came)
        assert spliced.dtype == np.float32 and not np.shares_memory(spliced, ordered)
        np.testing.assert_array_equal(spliced, expected)
    assert _contact._sorted_after(ordered, np.array([1e6], np.float32), came) is None


def test_sorted_lengths_with_pending_changes_agree_with_numpy():
    """The contact's live edge lengths as a sorted multiset with the changes of the last edits pending
    (``_SortedLengths``: values out of its base, values in, a value out that an earlier edit put in, the
    pending ones spliced in once they outgrow their share): after each of 60 random edits, with many equal
    values, every order statistic (``kth``), the median (``np.median``'s, bit for bit) and the values sorted
    are numpy's of the edited multiset; an edit taking out a value that is not there changes nothing."""
    rng = np.random.default_rng(5)
    for trial in range(6):
        multiset = (rng.integers(0, 9 if trial % 2 else 400, 300).astype(np.float32) / 7).tolist()
        kept = _contact._SortedLengths(np.sort(np.array(multiset, dtype=np.float32)))
        spliced = 0
        for _ in range(60):
            have = np.array(multiset, dtype=np.float32)
            out = rng.choice(len(have), int(rng.integers(0, 12)), replace=False)
            came = (rng.integers(-1, 10 if trial % 2 else 410, int(rng.integers(0, 12))) / 7).astype(np.float32)
            pending = len(kept.gone) + len(kept.came)
            assert kept.edit(have[out], came)
            spliced += len(kept.gone) + len(kept.came) < pending
            multiset = np.concatenate([np.delete(have, out), came]).tolist()
            expected = np.sort(np.array(multiset, dtype=np.float32))
            assert len(kept) == len(expected)
            assert [kept.kth(i) for i in range(len(expected))] == expected.tolist()
            assert kept.median() == float(np.median(expected))
            np.testing.assert_array_equal(kept.sorted(), expected)
        assert spliced and len(kept.came) + len(kept.gone) < len(kept.base)
        before = kept.sorted().copy()
        missing = np.array([1e6], np.float32)
        assert not kept.edit(missing, came)
        np.testing.assert_array_equal(kept.sorted(), before)
