"""The placement rule of ``gbuffer_export.sweep`` against an independent computation: box corners turned by a
rotation matrix, and the gap between two boxes measured axis by axis."""
import numpy as np

from gbuffer_export import sweep


def _moved(local, start):
    """The box of ``local`` at ``start``: its 8 corners turned about +Z by 0 or 180 degrees, then moved."""
    a = 0.0 if start[2] > 0 else np.pi
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    corners = np.array([[local[i, 0], local[j, 1], local[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    world = corners @ rot.T + np.array([start[0], start[1], 0.0])
    return world.min(axis=0), world.max(axis=0)


def _gap(lo_a, hi_a, lo_b, hi_b) -> float:
    """The largest separation on any axis (negative: they overlap on every axis)."""
    return float(np.max(np.maximum(lo_b - hi_a, lo_a - hi_b)))


def test_clear_starts_matches_turned_corners_and_axis_gaps():
    rng = np.random.default_rng(0)
    for _ in range(50):
        lo = rng.uniform(-0.5, 0.2, 3)
        local = np.stack([lo, lo + rng.uniform(0.1, 1.0, 3)])
        starts = np.column_stack([rng.uniform(-2, 2, 40), rng.uniform(-2, 2, 40), rng.choice([-1.0, 1.0], 40)])
        olo = rng.uniform(-2, 2, (6, 3))
        obstacles = np.stack([olo, olo + rng.uniform(0.05, 0.8, (6, 3))], axis=1)
        got = sweep.clear_starts(local, obstacles, starts, 0.02)
        for s, ok in zip(starts, got):
            a_lo, a_hi = _moved(local, s)
            expect = all(_gap(a_lo, a_hi, o[0], o[1]) >= 0.02 for o in obstacles)
            assert ok == expect, (s, ok)


def test_ground_and_what_a_foot_steps_onto_do_not_block():
    step = sweep.STEP_M
    obstacles = np.array([[[-8, -8, -0.1], [8, 8, 0.0]],          # the floor (flagged ground)
                          [[-1, -1, -0.008], [1, 1, 0.002]],        # a 1 cm slab, its top 2 mm up
                          [[0, 0, 0.0], [0.1, 0.1, step - 1e-3]],   # a pebble below the ankle
                          [[-3, -3, 0.5], [3, 3, 0.6]],             # a table top: blocks
                          [[0, 0, 0.0], [0.1, 0.1, step + 1e-3]]])  # above the ankle: blocks
    kept = sweep.blocking(obstacles, np.array([True, False, False, False, False]))
    assert np.array_equal(kept, obstacles[3:])


def test_clear_mask_judges_frame_by_frame_not_the_sweep():
    """A mover crossing the lane while the walker is elsewhere does not block it; one in its way at one frame does."""
    local = np.array([[-0.1, -0.1, 0.0], [0.1, 0.1, 1.8]])
    starts = np.array([[0.0, 0.0, 1.0], [5.0, 0.0, 1.0]])
    frames = []
    for t in range(5):
        walker = local + np.array([0.1 * t, 0.0, 0.0])               # walks +X
        mover = np.array([[[2.0 - 0.6 * t, -0.1, 1.0], [2.2 - 0.6 * t, 0.1, 1.2]]])  # comes -X towards start 0
        frames.append((walker, mover, np.zeros(1, bool)))
    assert sweep.clear_mask(frames, starts, 0.02).tolist() == [False, True]  # they meet at t = 3, at x 0.2..0.4
    late = [(w, m + np.array([10.0, 0.0, 0.0]), g) for w, m, g in frames]
    assert sweep.clear_mask(late, starts, 0.02).tolist() == [True, True]
    assert sweep.clear_mask(frames[:2], starts, 0.02).tolist() == [True, True]   # not yet met
    assert abs(sweep.half_width(frames) - 0.1) < 1e-12
