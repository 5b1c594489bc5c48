"""What the video determines: a 90% interval for every identified parameter, and whether it is identifiable.

A loss that barely changes when a parameter moves says the video does not determine that parameter
(DESIGN.md section 10: displacement-driven tools fix nu and the ratios of E, not E itself, unless weight,
inertia or a force gives a scale). The noise of the loss is measured on the loss itself, frame by frame:
for a trial value theta of one parameter (the others at the optimum theta*), the per-frame differences
d_t = l_t(theta) - l_t(theta*) give

    Delta L = sum_t d_t,    SE = sqrt(n) std(d_t),    z = Delta L / SE   (n compared frames),

a paired comparison of the two simulations over the frames. theta is excluded from the interval when z > z_c;
the interval runs from the lowest to the highest trial value that is not excluded (the hull of the values the
data do not exclude: a bump of the loss that excludes one trial does not cut off a farther one that fits as
well, nor one whose loss is below theta*'s, where theta* is not the slice's minimum), its ends interpolated
where z crosses z_c beyond them (:func:`interval_from_slice`). A parameter is identifiable when on
each side of theta* some trial value raises the loss significantly above its frame-to-frame noise, z > z_s
(:func:`significant_z`): a one-sided test at 5% per side of "the loss does not depend on theta", under which z
follows Student's t with n - 1 degrees of freedom. Slices go outward from theta* (log10 E by 0.1, 0.3, 1
decade, then to the search box's end; nu by 0.02, 0.06, then to the box's end: the largest nu at which the
optimum's E is still in the box, :func:`reachable_nu_max`) and stop at the first
significant value: a parameter is declared not identifiable only after the loss stayed within its noise over
the whole search box on a side.
One whose first gradient was zero is not identifiable, whatever its slice.

A slice holds the other parameter at the optimum, so where the video does not determine that partner (its value
is then arbitrary: usually its prior) the slice answers a question nobody asked. The profile likelihood would let
the partner go wherever the loss is least; a cheap version of it is taken instead: the parameter is sliced again
with its partner at each end of the partner's statistical interval, and combined with the slice through the
optimum by :func:`profiled` (a value lies inside when some slice does not exclude it, within that slice's own
search box: at a lower nu, E's reaches higher; a side counts as significant only when it does in every slice).
On the suite's ``impulse_paper`` at 1.5x (E kept at its prior, 10 kPa, for a true 100 kPa) the slice through
the optimum excluded the true nu 0.45 (interval [0.465, 0.49]), while at the upper end of E's interval, 809 kPa,
every nu from 0 to 0.49 fitted better than the optimum (docs/IDENTIFICATION.md section 1). It costs two more
slices (up to 16 simulations) per parameter whose partner is not identifiable, none where the video determines
both.

A rise must also matter: a trial whose loss rises by less than ``min_relative_rise`` of the optimum's loss
(identification's ``tol``, the relative change its optimiser counts as no progress) counts with at most the
interval's critical z, however consistent over the frames: it neither excludes its value from the interval nor
counts as significant (a rise below both thresholds keeps its z, so the interval's interpolated ends move only
where the floor decides). A fall that small does not make a value significantly better either (the report says
the optimisation stopped short only for a fall of at least the floor; the value still lies inside the interval,
as every value that fits better does). The frame-to-frame test alone cannot see such a floor: two simulations
that differ by float32 rounding differ consistently, frame after frame. Measured on CholecSeg8K's calibration
(docs/REAL_VIDEO.md section 6): moving the gallbladder's E by a factor 1 + 1e-7, 1 + 1e-5 or 1 + 1e-3 changed
every particle's trajectory by the same 5e-6 mm RMS (rounding; the tissue's whole simulated motion was 1.4 um)
and the loss by 0.7-1.0e-5 of its value, with |z| up to 1.2, while other trials of that run rose
"significantly" (z 2-3.6) by 2e-5 to 3e-4 of it: enough to call a parameter identifiable from noise. No stored
run of the suite or the demo has a trial above the critical z with a rise below 1e-3 (docs/IDENTIFICATION.md
section 1); both real clips have several.

The critical value (:func:`critical_z`). Near the optimum l_t(theta* + a) = l_t(theta*) + g_t a + h_t a^2 / 2
with sum_t g_t = 0, so Delta L = H a^2 / 2 (H = sum_t h_t) and SE = |a| sqrt(n) std(g_t): z = |a| / (2 s),
where s = sqrt(n) std(g_t) / H is the (sandwich) standard error of theta*. The level-``LEVEL`` interval
theta* +- q s is therefore z <= q / 2, with q the two-sided quantile of Student's t with n - 1 degrees of
freedom (the noise is estimated from n frames). For a quadratic per-frame loss with independent Gaussian
per-frame noise this is exact (``tests/test_uncertainty.py`` measures 90% coverage); z_c = 1.645, a
one-sided normal test of "theta is worse than theta*", gave 97-99.8% there (intervals about twice too
wide). The identifiability test needs more, z_s = q = 2 z_c (twice the interval's half-width on a quadratic
loss): with z_c alone a loss of pure noise, independent of theta, passes on both sides about 23% of the
time, with z_s about 6% (four trials per side; ``tests/test_uncertainty.py``). Frames whose errors are alike
(a model error shared by the whole clip) make that interval too narrow: ``endogsim bench suite`` reports how
often the true value falls inside (coverage).

The discretisation's error is one such shared error: a simulator that is not converged moves the optimum
itself (docs/IDENTIFICATION.md section 3). :func:`discretisation_error` measures it the way computational
mechanics does, with Roache's grid convergence index: the optimum along the same slice at a coarser
discretisation (grid / r, particle spacing x r, substeps / r) moves by epsilon, and the error of this one is
taken as GCI = F_s |epsilon| / (r^p - 1) (order p = 1: tool and boundary conditions set on grid nodes;
safety factor F_s = 3, Roache's for a study of two grids whose order is not verified). The reported
interval adds it to the statistical one side by side in quadrature, as independent errors (ASME V&V 20);
the statistical interval is kept beside it, and it alone decides whether the video moved a parameter away
from its prior. An interval that the discretisation's error stretches over the whole search box makes the
parameter not identifiable. A parameter whose statistical interval is the whole search box already has its
discretisation error not measured: nothing added to it could change the interval or the verdict (on the
real pulling clip nu's coarse walk: four simulations).

Where the statistical interval excludes a parameter's prior on one side only (the video bounds it there and
nowhere else: identification then reports the estimate, a one-sided one), the exclusion is checked at the
coarser discretisation too (:func:`prior_checked`): the loss at the prior (the others at the optimum) against the
optimum's, paired over the frames at that coarser discretisation, with the interval's own test (its critical z,
its least rise that counts). The claim "the video excludes the prior" then holds at the stated level only where
both discretisations make it (an intersection-union test: each is a test at that level, so their conjunction is
one too); where the coarser one does not exclude the prior, the exclusion is within the discretisation's error,
the prior stays (not identifiable) and the reported interval opens to the search box's end on the prior's side.
Until stop 83 the coarse test was the sign (z > 0: the coarser grid merely prefers the estimate), a weaker claim
than the one it checked, and it let through the suite's worst printed estimate: ``press_real`` at seed 1, E 223
kPa for a true 4 kPa (prior 5 kPa), coarse z +0.49 against a critical 0.88. On ``press_real`` at seed 2 the 1x
loss excluded the prior 5 kPa for an estimate of 82 kPa (truth 4 kPa) while the 0.7x loss preferred the prior (z
-1.12). The critical z costs seed 0's ``press_real`` nu estimate (0.422 for a true 0.42; coarse z +0.62), which
reverts to its prior 0.47. A check of consistency between two discretisations, not a better estimate
(docs/IDENTIFICATION.md section 5). One coarse simulation per one-sided estimate (the optimum's coarse simulation
is the coarse walk's).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from typing import TypeVar

import numpy as np
import torch

from endogsim.errors import EndoGSimError
from endogsim.materials.field import MaterialParams
from endogsim.warp_runtime import Cancelled, check_cancelled, run_independent

__all__ = ["LEVEL", "E_STEPS", "NU_STEPS", "GCI_ORDER", "GCI_SAFETY", "ParameterInterval", "Slice",
           "DiscretisationError", "least_rise", "counted_z", "paired_z", "critical_z", "significant_z",
           "interval_from_slice", "walk_slice", "walk_side", "slice_from_sides",
           "identifiability", "profiled", "discretisation_error", "coarse_side", "discretisation_from_sides", "widen",
           "reachable_nu_max", "parameter_intervals", "prior_checked"]

#: The intervals' level (two-sided): the probability that the true value lies inside.
LEVEL = 0.90
#: Slice steps away from the optimum: log10 E (decades) and nu; ``math.inf`` is the search box's end, so a
#: side with no significant rise nearby is tested once more at the farthest value identification could reach.
E_STEPS = (0.1, 0.3, 1.0, math.inf)
NU_STEPS = (0.02, 0.06, math.inf)
#: How near the search box's end (decades of E, units of nu) an optimum lies on it: nothing beyond was searched.
AT_BOX_END = 1e-4
#: The grid convergence index's assumed order of convergence and safety factor (Roache 1994): conditions on
#: grid nodes are first order in the cell size, but refining the suite's problems to 4x on a GPU showed
#: that order only without gravity (docs/IDENTIFICATION.md section 3), so the factor is Roache's for two
#: grids whose order is not verified, 3, not the 1.25 he allows where it is.
GCI_ORDER = 1.0
GCI_SAFETY = 3.0
R = TypeVar("R")


@dataclass
class ParameterInterval:
    """The evidence on one parameter of one object.

    Attributes:
        object_id, name: the object.
        parameter: "E" (Pa) or "nu".
        best: the identified value.
        interval: [lo, hi] 90% interval (Pa for E), clipped to the search box.
        search_box: [lo, hi] the values identification could reach (E's upper end depends on nu, and nu's on E:
            with ``partner_slices``, the hull of the boxes at the partner's values sliced).
        identifiable: the loss rises significantly above its noise on both sides within the search box (and
            the first gradient is not zero).
        reason: one line saying why (or why not).
        slice: [[value, Delta L, SE, z], ...] the trial values and their comparison with the optimum.
        first_gradient: the loss gradient with respect to this parameter at the first iteration (None when
            no iteration ran).
        critical_z: the z above which a trial value was excluded (:func:`critical_z`; None: fewer than 2
            compared frames, nothing excluded).
        significant_z: the z above which a trial value's loss counted as significantly higher
            (:func:`significant_z`; None likewise).
        min_relative_rise: a trial's loss had to rise by at least this share of the optimum's to count
            (:func:`counted_z`; 0: any rise counted).
        statistical_interval: [lo, hi] the interval from the loss's frame-to-frame noise alone (None: no
            discretisation error was measured, and ``interval`` is this one).
        discretisation: :class:`DiscretisationError` as a dict (None: not measured: no coarser simulation,
            one that failed (``reason`` says so), or a statistical interval that is the whole search box).
        partner_slices: the slices taken with the object's other parameter at the ends of its statistical
            interval, where the video does not determine that one (:func:`profiled`): [{"partner": "E" | "nu",
            "at": its value (Pa for E), "interval": [lo, hi] this slice's, "slice": [[value, Delta L, SE, z],
            ...]}]; empty where none was taken. ``interval``, ``statistical_interval`` and ``identifiable``
            take them in.
        correction: how far the refined correction moved the estimate and both intervals (decades for E, units
            of nu; :func:`~endogsim.identify.refined_correction.shifted_interval`); 0: not moved. ``slice`` and
            ``discretisation`` stay where they were measured.
        prior_check: where the statistical interval excludes the prior on one side, the same comparison at the
            coarser discretisation (:func:`prior_checked`): {"prior": Pa or -, "ratio": this grid over the coarse
            one, "delta_loss", "noise", "z": the coarse loss at the prior against the coarse loss at the optimum,
            "critical_z": the interval's, "excluded": the coarser discretisation excludes the prior too (z, counted
            as the interval counts it, above the critical z)}; None: not checked.
    """

    object_id: int
    name: str
    parameter: str
    best: float
    interval: list[float]
    search_box: list[float]
    identifiable: bool
    reason: str
    slice: list[list[float]] = field(default_factory=list)
    first_gradient: float | None = None
    critical_z: float | None = None
    significant_z: float | None = None
    min_relative_rise: float = 0.0
    statistical_interval: list[float] | None = None
    discretisation: dict | None = None
    partner_slices: list[dict] = field(default_factory=list)
    correction: float = 0.0
    prior_check: dict | None = None

    def to_json(self) -> dict:
        return asdict(self)


def least_rise(min_relative_rise: float, reference: dict[int, float]) -> float:
    """The least rise of the summed loss that counts: ``min_relative_rise`` of the optimum's summed per-frame
    ``reference`` loss (module docstring)."""
    return min_relative_rise * abs(float(sum(reference.values())))


def counted_z(delta: float, z: float, min_rise: float, ceiling: float) -> float:
    """The z a trial counts with: its :func:`paired_z` ``z``, or at most ``ceiling`` (the interval's critical z)
    where its loss rose by less than ``min_rise`` (module docstring: a rise too small to matter neither excludes
    a value nor is significant)."""
    return z if delta >= min_rise else min(z, ceiling)


def paired_z(per_frame: dict[int, float], reference: dict[int, float]) -> tuple[float, float, float]:
    """(Delta L, SE, z) of a trial's per-frame loss against the optimum's (frames both have)."""
    frames = sorted(set(per_frame) & set(reference))
    d = np.array([per_frame[t] - reference[t] for t in frames], dtype=np.float64)
    n = len(d)
    delta = float(d.sum())
    se = float(math.sqrt(n) * d.std(ddof=1)) if n > 1 else abs(delta)
    return delta, se, delta / max(se, 1e-12 * max(abs(delta), 1e-30))


def critical_z(n: int, level: float = LEVEL) -> float:
    """The z of :func:`paired_z` above which a trial value is excluded from the ``level`` interval, for ``n``
    compared frames: half the two-sided ``level`` quantile of Student's t with n - 1 degrees of freedom
    (module docstring; 0.917 for 10 frames at 90%, 0.822 in the limit). inf for n < 2: one frame has no
    frame-to-frame noise to compare with, so nothing is excluded."""
    if n < 2:
        return math.inf
    from scipy.stats import t

    return 0.5 * float(t.ppf(0.5 + level / 2, n - 1))


def significant_z(n: int, level: float = LEVEL) -> float:
    """The z of :func:`paired_z` above which a trial value's loss is significantly higher than the optimum's,
    for ``n`` compared frames: the one-sided (1 + ``level``) / 2 quantile of Student's t with n - 1 degrees of
    freedom (1.833 for 10 frames at 90%), twice :func:`critical_z`; inf for n < 2."""
    return 2.0 * critical_z(n, level)


def interval_from_slice(best: float, side_points: dict[int, list[tuple[float, float]]], box: tuple[float, float],
                        threshold: float) -> tuple[list[float], bool, bool]:
    """The interval around ``best`` from trial points on each side.

    Args:
        best: the optimum (in the slice's coordinate, e.g. log10 E).
        side_points: {-1: [(value, z), ...] going down, +1: [...] going up}, in order away from ``best``.
        box: the search box in the same coordinate.
        threshold: z above which a value is excluded.
    Returns:
        ([lo, hi], bounded below, bounded above).

    Every trial value that is not excluded (z <= ``threshold``, a loss below the optimum's included) lies
    inside, and so does everything between it and ``best``, even where a value in between was excluded: the
    interval is the hull of the values the data do not exclude, each tested against the optimum on its own.
    A side's end is where z crosses ``threshold`` beyond the farthest such value, or the box's end when no
    value beyond it was excluded. Two slices showed why the connected set around ``best`` is not enough: on
    ``impulse_paper`` a bump of z 1.07 at 1.26x the optimum cut E's interval at 1.22x, while the loss was
    lower at 10x and 44x, where the true E lies; on the demo's seed 7 (optimum 954 Pa) z 1.29 at 1201 Pa cut
    it at 1254 Pa, while 1904 Pa was not excluded (z 0.84) and the true E is 2500 Pa.
    """
    ends, bounded = {}, {}
    for side, pts in side_points.items():
        inside = [k for k, (_, z) in enumerate(pts) if z <= threshold]
        start = inside[-1] + 1 if inside else 0
        last_v, last_z = pts[start - 1] if start else (best, 0.0)
        ends[side], bounded[side] = (box[0] if side < 0 else box[1]), False
        if start < len(pts):  # the first value past the farthest one inside is excluded: the end lies between
            v, z = pts[start]
            w = (threshold - last_z) / (z - last_z) if z != last_z else 1.0
            ends[side], bounded[side] = last_v + w * (v - last_v), True
    return [ends[-1], ends[1]], bounded[-1], bounded[1]


@dataclass
class Slice:
    """One parameter's slice (:func:`walk_slice`).

    Attributes:
        interval: [lo, hi] in the slice's coordinate (the search box where a side is not bounded).
        bounded: (below, above): a trial value was excluded on that side (z > the interval's critical z).
        significant: (below, above): a trial value's loss rose significantly above the noise on that side.
        records: [[value, Delta L, SE, z], ...] in the order evaluated.
        failures: [(value, message), ...] trial values whose simulation failed (it ends that side's walk:
            a simulation that cannot run is no evidence either way).
    """

    interval: list[float]
    bounded: tuple[bool, bool]
    significant: tuple[bool, bool]
    records: list[list[float]]
    failures: list[tuple[float, str]] = field(default_factory=list)


def walk_slice(best: float, steps: tuple[float, ...], box: tuple[float, float],
               compare: Callable[[float], tuple[float, float, float]], threshold: float,
               significance: float | None = None, min_rise: float = 0.0) -> Slice:
    """Walk one parameter's slice outward from ``best``: its interval and what it shows on each side.

    On each side (down, then up) the trial values are ``best -+ step`` for ``steps``, clipped to ``box``; a
    side stops at the first value whose z exceeds ``significance`` (or, without it, ``threshold``), where
    the box ends, or at a trial whose simulation fails (:class:`~endogsim.errors.EndoGSimError`, kept in
    ``failures``). The interval's end on a side is where z first crosses ``threshold``.

    Args:
        best: the optimum (slice coordinate, e.g. log10 E).
        steps: distances from ``best``, increasing (``math.inf``: the box's end).
        box: the search box in the same coordinate.
        compare: trial value -> (Delta L, SE, z) against the optimum (:func:`paired_z`).
        threshold: z above which a value is excluded from the interval (:func:`critical_z`).
        significance: z above which the loss counts as significantly higher (:func:`significant_z`).
        min_rise: the least rise of the loss (Delta L) that counts (:func:`counted_z`).
    """
    stop = _stop_z(threshold, significance)
    down, up = (walk_side(best, steps, box, compare, stop, side, min_rise, threshold) for side in (-1, 1))
    return slice_from_sides(best, box, threshold, stop, down, up)


def _stop_z(threshold: float, significance: float | None) -> float:
    return threshold if significance is None else max(threshold, significance)


#: One side of a slice (:func:`walk_side`): [(value, counted z)], records [[value, Delta L, SE, z]], failures
#: [(value, message)].
SliceSide = tuple[list[tuple[float, float]], list[list[float]], list[tuple[float, str]]]


def walk_side(best: float, steps: tuple[float, ...], box: tuple[float, float],
              compare: Callable[[float], tuple[float, float, float]], stop: float, side: int,
              min_rise: float = 0.0, ceiling: float = math.inf) -> SliceSide:
    """One side (-1: down, 1: up) of :func:`walk_slice`: trial values ``best + side * step`` until one's
    counted z (:func:`counted_z` with ``min_rise`` and ``ceiling``) exceeds ``stop``, the box ends, or a
    simulation fails."""
    points: list[tuple[float, float]] = []
    records: list[list[float]] = []
    failures: list[tuple[float, str]] = []
    for step in steps:
        v = min(max(best + side * step, box[0]), box[1])
        if abs(v - best) < 1e-9 or (points and abs(v - points[-1][0]) < 1e-9):
            break  # the box ends here
        try:
            delta, se, z = compare(v)
        except EndoGSimError as e:
            failures.append((v, str(e)))
            break
        points.append((v, counted_z(delta, z, min_rise, ceiling)))
        records.append([v, delta, se, z])
        if points[-1][1] > stop:
            break
    return points, records, failures


def slice_from_sides(best: float, box: tuple[float, float], threshold: float, stop: float,
                     down: SliceSide, up: SliceSide) -> Slice:
    """The :class:`Slice` of the two sides walked by :func:`walk_side` (records and failures down, then up)."""
    sides = {-1: down[0], 1: up[0]}
    interval, b_lo, b_hi = interval_from_slice(best, sides, box, threshold)
    sig = tuple(any(z > stop for _, z in sides[side]) for side in (-1, 1))
    return Slice(interval, (b_lo, b_hi), sig, down[1] + up[1], down[2] + up[2])


def identifiability(sl: Slice, first_gradient: float | None, span: str, significance: float) -> tuple[bool, str]:
    """Whether a parameter is identifiable from its slice, and one line saying why (or why not).

    Args:
        sl: from :func:`walk_slice`.
        first_gradient: the loss gradient at the first iteration (exactly 0: the video does not constrain it).
        span: how far the slice went, for the message (e.g. "the search box").
        significance: the z a trial needed on each side (:func:`significant_z`).
    """
    if first_gradient is not None and first_gradient == 0.0:
        return False, "the loss gradient was exactly zero: the video does not constrain it"
    if not math.isfinite(significance):
        return False, "fewer than 2 compared frames: no frame-to-frame noise to measure the loss against"
    if all(sl.significant):
        return True, (f"the loss rises significantly above its frame-to-frame noise (z > {significance:.4g}) "
                      "on both sides")
    if not any(sl.bounded):
        return False, f"the loss changes by less than its frame-to-frame noise over {span}"
    flat = [name for name, sig in zip(("below", "above"), sl.significant) if not sig]
    return False, (f"the loss does not rise significantly above its frame-to-frame noise (z > {significance:.4g}) "
                   f"{' or '.join(flat)} the optimum within {span}")


def profiled(center: Slice, partners: list[Slice]) -> Slice:
    """One parameter's slice across its partner's values: ``center`` (the partner at the optimum) and
    ``partners`` (the same slice with the partner elsewhere: at the ends of its statistical interval), a coarse
    profile of the loss (module docstring). A value lies inside when some slice does not exclude it, so the
    interval is the hull of the slices' intervals, each within its own search box (E's reaches higher at a lower
    nu, nu's at a lower E); a side is bounded, or significant, only where every slice is (a value is ruled out
    only when it is whatever the partner). The records are ``center``'s (the partners' stay with them); the
    failures are all of them."""
    every = [center, *partners]
    interval = [min(s.interval[0] for s in every), max(s.interval[1] for s in every)]
    bounded = tuple(all(s.bounded[i] for s in every) for i in range(2))
    significant = tuple(all(s.significant[i] for s in every) for i in range(2))
    return Slice(interval, bounded, significant, center.records, [f for s in every for f in s.failures])


@dataclass
class DiscretisationError:
    """How far a parameter's optimum moves at a coarser discretisation, and the error bar that implies.

    Attributes:
        ratio: r, this discretisation's grid over the coarse one's (> 1).
        coarse_best: the optimum along the parameter's slice at the coarse discretisation (slice coordinate:
            log10 E or nu).
        shift: coarse_best - best (decades of E, or nu).
        half_width: the grid convergence index GCI_SAFETY |shift| / (r^GCI_ORDER - 1), in the same coordinate.
        lower_bound: the coarse loss still fell at the last value its walk reached (a failed simulation ended
            it short of the box's end): the coarse optimum lies there or beyond, and ``shift`` is a lower bound.
        profile: [[value, coarse loss], ...] in the order evaluated.
    """

    ratio: float
    coarse_best: float
    shift: float
    half_width: float
    lower_bound: bool
    profile: list[list[float]]


def discretisation_error(best: float, steps: tuple[float, ...], box: tuple[float, float],
                         coarse_loss: Callable[[float], float], ratio: float) -> DiscretisationError:
    """The optimum of ``coarse_loss`` along a slice through ``best``, and the grid convergence index it gives.

    On each side the walk takes ``steps`` outward from ``best`` (as :func:`walk_slice`, clipped to ``box``)
    while the coarse loss keeps falling, and stops at the first value that is no lower, at the box's end or
    at a simulation that fails (:class:`~endogsim.errors.EndoGSimError`). The coarse optimum is the least
    value evaluated, refined by the parabola through it and its two neighbours when it has one on each side.

    Args:
        best: the optimum at the identification's discretisation (slice coordinate).
        steps: distances from ``best``, increasing (``math.inf``: the box's end).
        box: the search box in the same coordinate.
        coarse_loss: trial value -> the loss at the coarse discretisation (the other parameters at the optimum).
        ratio: r > 1, the identification's grid over the coarse grid.
    """
    if not ratio > 1:
        raise ValueError(f"a coarser discretisation has a grid ratio > 1, got {ratio}")
    at_best = coarse_loss(best)  # each side starts there: simulated once
    sides = [coarse_side(best, steps, box, lambda v: at_best if v == best else coarse_loss(v), side)
             for side in (-1, 1)]
    return discretisation_from_sides(best, ratio, *sides)


#: One side of a coarse walk (:func:`coarse_side`): {value: coarse loss} (``best`` included) and whether a
#: failed simulation ended it.
CoarseSide = tuple[dict[float, float], bool]


def coarse_side(best: float, steps: tuple[float, ...], box: tuple[float, float],
                coarse_loss: Callable[[float], float], side: int) -> CoarseSide:
    """One side (-1: down, 1: up) of :func:`discretisation_error`'s walk. A failure of the simulation at
    ``best`` itself is raised (there is no walk without it)."""
    points = {best: coarse_loss(best)}
    last_v, last_l = best, points[best]
    for step in steps:
        v = min(max(best + side * step, box[0]), box[1])
        if abs(v - last_v) < 1e-9:
            break  # the box ends here
        try:
            loss = coarse_loss(v)
        except EndoGSimError:
            return points, True
        points[v] = loss
        if not loss < last_l:
            break
        last_v, last_l = v, loss
    return points, False


def discretisation_from_sides(best: float, ratio: float, down: CoarseSide, up: CoarseSide) -> DiscretisationError:
    """The :class:`DiscretisationError` of the two sides walked by :func:`coarse_side`."""
    points = {**down[0], **up[0]}
    xs = sorted(points)
    i = min(range(len(xs)), key=lambda k: (points[xs[k]], abs(xs[k] - best)))  # a tie: the nearer value
    x = xs[i]
    if 0 < i < len(xs) - 1:  # the parabola's vertex through the least value and its neighbours
        (x0, x1, x2), (y0, y1, y2) = xs[i - 1:i + 2], (points[v] for v in xs[i - 1:i + 2])
        den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
        if den != 0:
            x = min(max(x1 - 0.5 * ((x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)) / den, x0), x2)
    lower = (i == 0 and down[1]) or (i == len(xs) - 1 and up[1])
    shift = x - best
    return DiscretisationError(ratio=float(ratio), coarse_best=float(x), shift=float(shift),
                               half_width=GCI_SAFETY * abs(shift) / (ratio ** GCI_ORDER - 1.0),
                               lower_bound=bool(lower), profile=[[v, points[v]] for v in points])


def reachable_nu_max(params: MaterialParams, slot: int,
                     box_log10_E: Callable[[MaterialParams], tuple[list[float], list[float]]]) -> float:
    """The largest nu (within ``params.nu_bounds``) at which slot ``slot``'s log10 E, the optimum's, is still
    inside the search box: the upper end of the box for E falls as nu rises (the CFL rule: a stiffer P wave
    needs more substeps), so a stiff optimum is not reachable at every nu. Identification cannot go beyond it,
    and neither does nu's slice: its trials there would be no part of the search box, and cost more substeps
    than ``max_substeps`` (EndoNeRF pulling's optimum E 118 kPa at nu 0.49: 554 substeps per frame, 4x the
    optimum's 134). The optimum's own nu when it is already on that edge (or beyond it)."""
    log10_E = float(params.log10_E.detach()[slot])
    lo, hi = float(params.nu().detach()[slot]), params.nu_bounds[1]

    def inside(nu: float) -> bool:
        return box_log10_E(_with_value(params, slot, "nu", nu))[1][slot] >= log10_E - 1e-9

    if inside(hi):
        return hi
    if lo >= hi or not inside(lo):
        return lo
    for _ in range(40):  # the box's upper end falls monotonically with nu: bisect to ~1e-12 of the range
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if inside(mid) else (lo, mid)
    return lo


def spans(interval: list[float], box: tuple[float, float]) -> bool:
    """Whether ``interval`` is the whole of ``box`` (to 1e-9)."""
    return interval[0] <= box[0] + 1e-9 and interval[1] >= box[1] - 1e-9


def widen(interval: list[float], best: float, half_width: float, box: tuple[float, float]) -> list[float]:
    """``interval`` around ``best`` with ``half_width`` added to each side in quadrature (independent errors),
    clipped to ``box``; a side already at the box's end stays there."""
    lo, hi = interval
    return [max(box[0], best - math.hypot(best - lo, half_width)), min(box[1], best + math.hypot(hi - best, half_width))]


def parameter_intervals(
    params: MaterialParams,
    object_names: dict[int, str],
    evaluate: Callable[[MaterialParams], dict[int, float]],
    box_log10_E: Callable[[MaterialParams], tuple[list[float], list[float]]],
    optimise_nu: bool,
    first_gradients: dict[str, list[float]] | None = None,
    level: float = LEVEL,
    coarse_evaluate: Callable[[MaterialParams], dict[int, float]] | None = None,
    coarse_ratio: float | None = None,
    workers: int = 1,
    reference: dict[int, float] | None = None,
    then: Callable[[list[ParameterInterval]], object] | None = None,
    on_trial: Callable[[dict], None] | None = None,
    min_relative_rise: float = 0.0,
) -> list[ParameterInterval]:
    """Intervals and identifiability of every slot's log10 E (and nu) around the optimum ``params``.

    Args:
        params: the optimum (not modified; trial copies are evaluated).
        object_names: {object id: name}.
        evaluate: trial parameters -> the per-frame loss {frame: value} (a simulation and its render).
        box_log10_E: parameters -> ([lower], [upper]) log10 E bounds per slot (upper depends on nu).
        optimise_nu: whether nu was identified (else only E gets an interval).
        first_gradients: {"log10_E": [...], "nu_raw": [...]} per slot at the first iteration.
        level: the intervals' level (the critical z follows from it and the number of compared frames).
        coarse_evaluate: like ``evaluate`` at a coarser discretisation (None: no discretisation error is
            measured); its optimum along each slice gives :func:`discretisation_error`, added to the interval.
        coarse_ratio: this discretisation's grid over the coarse one's (> 1; with ``coarse_evaluate``).
        workers: trial simulations run at a time (:func:`~endogsim.warp_runtime.run_independent`; ``evaluate`` and
            ``coarse_evaluate`` must then be safe to call from several threads). The result does not depend on it.
        reference: ``evaluate(params)`` when it is known already (the optimisation's iteration at the optimum
            computed it), else None: it is evaluated first.
        then: a task queued after the coarse walks, called with the intervals the slices alone give (no
            discretisation error measured) once every slice has ended: work that needs only those (e.g.
            evaluating the materials they imply) runs while the coarse walks do. Its result is dropped.
        on_trial: called after every trial simulation, from the thread that ran it (progress display), with
            {"object": name, "parameter": "E" | "nu", "value": Pa or -, "grid": "fine" | "coarse", "at": where the
            partner was held when not at the optimum (e.g. "nu = 0.490"), else ""}.
        min_relative_rise: the least rise of the loss, relative to the optimum's, that counts (module
            docstring, :func:`counted_z`; identification passes its ``tol``).
    """
    if reference is None:
        # The optimum first, alone: every trial is compared with it, and the first launches of Warp's kernels
        # (which build them) are not safe from two threads.
        reference = evaluate(params)
    threshold, significance = critical_z(len(reference), level), significant_z(len(reference), level)
    stop = _stop_z(threshold, significance)
    min_rise = least_rise(min_relative_rise, reference)
    cancel = threading.Event()  # set when a trial fails: the other walks stop starting trials
    # Every coarse walk starts at the optimum: the first to get there simulates it, the other waits for it
    # (a failure there is each walk's, and each says so).
    coarse_loss = None if coarse_evaluate is None else _shared_loss(coarse_evaluate, cancel)

    def tell(name: str, what: str, v: float, grid: str, at: str = "") -> None:
        if on_trial is not None:
            on_trial({"object": name, "parameter": what, "value": _value(what, v), "grid": grid, "at": at})

    # Every slice's two sides are independent simulations, and so are the two sides of its coarse walk, which
    # need only know whether the slice left the interval short of the search box (else no error added to it
    # could change it: the walk is not run), and of its slices at the partner's interval ends, which need the
    # partner's slice. Run them all, ``workers`` at a time, the slices first (the others start after them, so
    # what they wait for is running), then assemble each interval in order.
    def search_box(trial: MaterialParams, slot: int, what: str) -> tuple[float, float]:
        """Slot ``slot``'s search box for log10 E or nu at ``trial`` (E's upper end depends on nu, and nu's on E)."""
        if what == "E":
            return tuple(b[slot] for b in box_log10_E(trial))
        return params.nu_bounds[0], reachable_nu_max(trial, slot, box_log10_E)

    plans, sides, walks, ended = [], [], [], []  # ended: each slice side's result, when it has one
    for slot in range(params.log10_E.shape[0]):
        oids = [o for o in params.object_ids if params.slot(o) == slot]
        name = ", ".join(object_names.get(o, str(o)) for o in oids)
        specs = [("E", E_STEPS, search_box(params, slot, "E"), float(params.log10_E.detach()[slot]))]
        if optimise_nu:
            specs.append(("nu", NU_STEPS, search_box(params, slot, "nu"), float(params.nu().detach()[slot])))
        for what, steps, box, best in specs:
            def compare(v: float, slot=slot, what=what, name=name) -> tuple[float, float, float]:
                check_cancelled(cancel)
                per_frame = evaluate(_with_value(params, slot, what, v))
                tell(name, what, v, "fine")
                return paired_z(per_frame, reference)

            def coarse_trial(v: float, slot=slot, what=what, best=best, name=name) -> float:
                # The optimum itself is ``params`` exactly (nu's round trip through its raw value would change
                # the last bits, and simulate it again).
                loss = coarse_loss(params if v == best else _with_value(params, slot, what, v))
                tell(name, what, v, "coarse")
                return loss

            down, up = Future(), Future()
            ended += [down, up]

            def coarse_walk(side: int, steps=steps, box=box, best=best, down=down, up=up,
                            trial=coarse_trial) -> CoarseSide | EndoGSimError | None:
                """One side of the parameter's coarse walk; the failure that left none (the interval then stays
                the statistical one); None where the slice's interval is the whole search box."""
                try:
                    interval = slice_from_sides(best, box, threshold, stop, down.result(), up.result()).interval
                except BaseException:  # the slice's own error is the one raised
                    raise Cancelled() from None
                if spans(interval, box):
                    return None
                try:
                    return coarse_side(best, steps, box, trial, side)
                except EndoGSimError as e:
                    return e

            plans.append((slot, oids, name, what, steps, box, best))
            sides += [partial(_resolving, down, partial(walk_side, best, steps, box, compare, stop, -1, min_rise,
                                                       threshold)),
                      partial(_resolving, up, partial(walk_side, best, steps, box, compare, stop, 1, min_rise,
                                                     threshold))]
            walks += [partial(coarse_walk, -1), partial(coarse_walk, 1)] if coarse_loss is not None else []

    def first_gradient(slot: int, what: str) -> float | None:
        if first_gradients is None:
            return None
        return first_gradients.get("log10_E" if what == "E" else "nu_raw", [None] * (slot + 1))[slot]

    # Where the video does not determine a parameter, its partner's slice through the optimum is conditional on
    # an arbitrary value of it (usually its prior): the partner is sliced again at the ends of the parameter's
    # statistical interval (module docstring). Each such side waits for the parameter's slice to end.
    partner_plans = [(k, j, end, side) for k, plan in enumerate(plans) for j, other in enumerate(plans)
                     if j != k and other[0] == plan[0] for end in (0, 1) for side in (-1, 1)]
    partner_ended = [Future() for _ in partner_plans]

    def partner_side(k: int, j: int, end: int, side: int) -> tuple[float, tuple[float, float], SliceSide] | None:
        """One side of plan ``k``'s slice with plan ``j``'s parameter at its interval's end ``end`` (0: lower):
        (that value, the box there, the side); None where the video determines plan ``j``'s parameter."""
        slot, _, name, what, steps, _, best = plans[k]
        _, _, _, partner, _, partner_box, partner_best = plans[j]
        try:
            sl = slice_from_sides(partner_best, partner_box, threshold, stop, ended[2 * j].result(),
                                  ended[2 * j + 1].result())
        except BaseException:  # the slice's own error is the one raised
            raise Cancelled() from None
        if identifiability(sl, first_gradient(slot, partner), "the search box", significance)[0]:
            return None
        at = _with_value(params, slot, partner, sl.interval[end])
        where = f"E = {_value(partner, sl.interval[end]):.4g} Pa" if partner == "E" else f"nu = {sl.interval[end]:.3f}"
        box = search_box(at, slot, what)

        def compare(v: float) -> tuple[float, float, float]:
            check_cancelled(cancel)
            per_frame = evaluate(_with_value(at, slot, what, v))
            tell(name, what, v, "fine", where)
            return paired_z(per_frame, reference)

        return sl.interval[end], box, walk_side(best, steps, box, compare, stop, side, min_rise, threshold)

    def interval_of(k: int, down: SliceSide, up: SliceSide, coarse: list, partners: list) -> ParameterInterval:
        """Plan ``k``'s interval from its slice's sides, its coarse walk's ([None, None]: none) and its slices at
        the partner's interval ends ([(value, box, side)] down and up at the lower end, then at the upper; None
        where none was taken)."""
        slot, oids, name, what, steps, box, best = plans[k]
        own_box = box  # at the optimum (``box`` grows to the hull over the partner's slices)
        to_value = partial(_value, what)
        partner = "nu" if what == "E" else "E"
        err = next((c for c in coarse if isinstance(c, EndoGSimError)), None)
        if err is None and coarse[0] is not None:
            err = discretisation_from_sides(best, float(coarse_ratio), *coarse)
        center = slice_from_sides(best, box, threshold, stop, down, up)
        others, partner_slices = [], []
        for down_there, up_there in zip(partners[::2], partners[1::2]):  # at the partner's lower end, its upper
            if down_there is not None:
                at, box_there, _ = down_there
                box = (min(box[0], box_there[0]), max(box[1], box_there[1]))  # the search box across the partner
                others.append(slice_from_sides(best, box_there, threshold, stop, down_there[2], up_there[2]))
                partner_slices.append({"partner": partner, "at": _value(partner, at),
                                       "interval": [to_value(v) for v in others[-1].interval],
                                       "slice": [[to_value(r[0])] + r[1:] for r in others[-1].records]})
        sl = profiled(center, others)
        (lo, hi), records = sl.interval, sl.records
        g0 = first_gradient(slot, what)
        ok, reason = identifiability(sl, g0, "the search box", significance)
        if partner_slices:
            reason += (f"; taken over {partner_slices[0]['partner']}'s interval too (not identifiable), whose ends "
                       "give " + ", ".join(f"[{p['interval'][0]:.4g}, {p['interval'][1]:.4g}]" for p in partner_slices)
                       + f" against [{to_value(center.interval[0]):.4g}, {to_value(center.interval[1]):.4g}] at "
                       "the optimum")
        small = [r for r in records if counted_z(r[1], r[3], min_rise, threshold) < r[3]]  # the floor decided
        if small:
            reason += (f"; {len(small)} trial value(s) whose loss rose consistently over the frames but by less "
                       f"than {min_relative_rise:.2g} of its value did not count (z "
                       + ", ".join(f"{r[3]:.3g}" for r in small) + ")")
        better = [r for r in records if r[3] < -significance and -r[1] >= min_rise]  # the floor, as for a rise
        if better:
            r = min(better, key=lambda r: r[1])
            reason += (f"; the loss is significantly lower at {what} = {to_value(r[0]):.4g} (z {r[3]:.3g}) than at "
                       "the estimate: the optimisation stopped short of the slice's minimum, and the interval "
                       "reaches past it")
        for v, message in sl.failures:
            reason += f"; the simulation at {what} = {to_value(v):.4g} failed ({message}), which ended the slice there"
        on_end = [(side, edge) for side, edge in zip(("lower", "upper"), own_box) if abs(best - edge) <= AT_BOX_END]
        if on_end:  # nothing beyond it was searched: the value is the box's (on real video, a model error's sink)
            side, edge = on_end[0]
            past = "below" if side == "lower" else "beyond"
            reason += (f"; the optimum lies on the search box's {side} end ({to_value(edge):.4g}"
                       f"{' Pa' if what == 'E' else ''}): the loss is least there of all the values searched, so the "
                       f"video prefers this end or {past} it, and the optimum is the box's, not a measurement")
        statistical, disc = None, None
        if isinstance(err, EndoGSimError):
            reason += f"; the discretisation error was not measured (the coarser simulation failed: {err})"
        elif err is not None:
            statistical = [to_value(lo), to_value(hi)]
            lo, hi = widen([lo, hi], best, err.half_width, box)
            disc = asdict(err)
            disc["coarse_best"] = to_value(err.coarse_best)
            disc["profile"] = [[to_value(v), loss] for v, loss in err.profile]
            if ok and spans([lo, hi], box):
                # The video determines it at this discretisation, but the discretisation itself does
                # not: an interval over the whole search box is "not identifiable" (issue 21).
                ok = False
                reason = (f"the loss rises significantly on both sides, but the discretisation's error "
                          f"(the optimum moves {err.shift:+.3g} on a grid {err.ratio:.2f}x coarser) spans "
                          "the search box")
        return ParameterInterval(
            object_id=oids[0], name=name, parameter=what, best=to_value(best),
            interval=[to_value(lo), to_value(hi)], search_box=[to_value(box[0]), to_value(box[1])],
            identifiable=ok, reason=reason,
            slice=[[to_value(r[0])] + r[1:] for r in records], first_gradient=g0,
            critical_z=threshold if math.isfinite(threshold) else None,
            significant_z=significance if math.isfinite(significance) else None,
            min_relative_rise=min_relative_rise, statistical_interval=statistical, discretisation=disc,
            partner_slices=partner_slices)

    def assemble(slices: list[SliceSide], partners: list, coarse: list[CoarseSide | EndoGSimError | None]
                 ) -> list[ParameterInterval]:
        """Every parameter's interval from its slice's two sides, its slices at the partner's interval ends
        (:func:`partner_side`'s, in ``partner_plans``' order) and its coarse walk's (None: none)."""
        return [interval_of(k, slices[2 * k], slices[2 * k + 1], coarse[2 * k: 2 * k + 2] or [None, None],
                            [r for (i, *_), r in zip(partner_plans, partners) if i == k] or [None] * 4)
                for k in range(len(plans))]

    partner_tasks = [partial(_resolving, f, partial(partner_side, *pp)) for f, pp in zip(partner_ended, partner_plans)]
    tasks = sides + partner_tasks + walks
    if then is not None:
        def after_slices() -> None:
            try:
                slices, partners = [f.result() for f in ended], [f.result() for f in partner_ended]
            except BaseException:  # a slice's own error is the one raised
                raise Cancelled() from None
            then(assemble(slices, partners, []))

        tasks.append(after_slices)
    results = run_independent(tasks, workers, cancel)
    n, m = len(sides), len(partner_tasks)
    return assemble(results[:n], results[n:n + m], results[n + m:n + m + len(walks)])


def prior_checked(intervals: list[ParameterInterval], params: MaterialParams, priors: dict[tuple[int, str], float],
                  coarse_evaluate: Callable[[MaterialParams], dict[int, float]], ratio: float, workers: int = 1,
                  on_trial: Callable[[dict], None] | None = None) -> list[ParameterInterval]:
    """``intervals`` with the one-sided exclusions of a prior checked at a coarser discretisation (module
    docstring).

    Args:
        intervals: from :func:`parameter_intervals` around ``params``.
        params: the optimum.
        priors: {(object id, "E" | "nu"): the prior (Pa or -)} of the intervals to check: those whose statistical
            interval excludes the prior on one side (identification's one-sided estimates); the others are
            returned as they are.
        coarse_evaluate: trial parameters -> the per-frame loss at the coarser discretisation (the one the
            intervals' discretisation error was measured at: its result at ``params`` is already known there).
        ratio: this discretisation's grid over the coarse one's (> 1).
        workers: trial simulations run at a time; the result does not depend on it.
        on_trial: as :func:`parameter_intervals`'.
    Returns:
        The intervals, in order. A checked one carries ``prior_check``; where the coarse loss at the prior is
        not higher than at the optimum by the interval's own test (its critical z; a rise below its least rise
        counts with at most that z), its reported ``interval`` reaches the search box's end on the prior's side
        and its ``reason`` says why. One whose coarse simulation fails is returned unchecked, its
        reason saying so.
    """
    todo = [k for k, iv in enumerate(intervals) if (iv.object_id, iv.parameter) in priors]
    if not todo:
        return list(intervals)

    def unchecked(iv: ParameterInterval, e: EndoGSimError) -> ParameterInterval:
        return replace(iv, reason=iv.reason + f"; its prior was not checked at the coarser discretisation (the "
                                              f"simulation failed: {e})")

    try:  # the coarse walks simulated the optimum already (remembered): first, alone, in any case
        reference = coarse_evaluate(params)
    except EndoGSimError as e:
        return [unchecked(iv, e) if k in todo else iv for k, iv in enumerate(intervals)]

    def check(k: int) -> ParameterInterval:
        iv = intervals[k]
        prior = priors[(iv.object_id, iv.parameter)]
        at = math.log10(prior) if iv.parameter == "E" else prior
        try:
            per_frame = coarse_evaluate(_with_value(params, params.slot(iv.object_id), iv.parameter, at))
        except EndoGSimError as e:
            return unchecked(iv, e)
        if on_trial is not None:
            on_trial({"object": iv.name, "parameter": iv.parameter, "value": prior, "grid": "coarse", "at": ""})
        delta, se, z = paired_z(per_frame, reference)
        threshold = iv.critical_z if iv.critical_z is not None else critical_z(len(set(per_frame) & set(reference)))
        min_rise = least_rise(iv.min_relative_rise, reference)
        record = {"prior": prior, "ratio": float(ratio), "delta_loss": delta, "noise": se, "z": z,
                  "critical_z": threshold, "excluded": counted_z(delta, z, min_rise, threshold) > threshold}
        unit = " Pa" if iv.parameter == "E" else ""
        if record["excluded"]:
            return replace(iv, prior_check=record, reason=iv.reason + (
                f"; the video's noise excludes the prior {prior:.4g}{unit}, and on a grid {ratio:.2f}x coarser too "
                f"(z {z:+.2f} > {threshold:.2f})"))
        lo, hi = iv.interval
        below = prior < iv.best
        interval = [iv.search_box[0], hi] if below else [lo, iv.search_box[1]]
        reason = (f"; the video's noise excludes the prior {prior:.4g}{unit} at this discretisation, but not on a "
                  f"grid {ratio:.2f}x coarser (z {z:+.2f}, critical {threshold:.2f}): the exclusion is within the "
                  f"discretisation's error, so the prior stays and the interval reaches the search box's "
                  f"{'lower' if below else 'upper'} end")
        return replace(iv, interval=interval, reason=iv.reason + reason, prior_check=record)

    checked = run_independent([partial(check, k) for k in todo], workers)
    out = list(intervals)
    for k, iv in zip(todo, checked):
        out[k] = iv
    return out


def _resolving(future: Future, task: Callable[[], R]) -> R:
    """``task()``, its result or its error also given to ``future`` (for a task that waits on it)."""
    try:
        result = task()
    except BaseException as e:
        future.set_exception(e)
        raise
    future.set_result(result)
    return result


def _shared_loss(evaluate: Callable[[MaterialParams], dict[int, float]],
                 cancel: threading.Event | None = None) -> Callable[[MaterialParams], float]:
    """``sum(evaluate(trial).values())``, each trial computed once, whichever thread asks first (the others
    wait for it): every parameter's coarse walk starts at the optimum."""
    lock, cache = threading.Lock(), {}

    def loss(trial: MaterialParams) -> float:
        key = (tuple(trial.log10_E.tolist()), tuple(trial.nu_raw.tolist()))
        with lock:
            future, owner = cache.get(key), key not in cache
            if owner:
                future = cache[key] = Future()
        if owner:
            try:
                check_cancelled(cancel)
                future.set_result(float(sum(evaluate(trial).values())))
            except BaseException as e:  # every waiter gets the same failure
                future.set_exception(e)
        return future.result()

    return loss


def _value(what: str, x: float) -> float:
    """The value of ``what`` ("E": Pa, "nu") at slice coordinate ``x`` (log10 E, nu): slices walk E in decades."""
    return 10.0 ** x if what == "E" else x


def _with_value(params: MaterialParams, slot: int, what: str, value: float) -> MaterialParams:
    """A detached copy of ``params`` with slot ``slot``'s log10 E (what "E") or nu set to ``value``."""
    from endogsim.materials.field import nu_to_raw

    log10_E = params.log10_E.detach().clone()
    nu_raw = params.nu_raw.detach().clone()
    with torch.no_grad():
        if what == "E":
            log10_E[slot] = value
        else:
            nu_raw[slot] = nu_to_raw(value, *params.nu_bounds)
    return MaterialParams(log10_E, nu_raw, list(params.object_ids), params.nu_bounds, params.global_material)
