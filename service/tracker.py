"""Per-subject labeling, the paper's loop made robust: `step(model, state, points, free, t_ns)`.

1. Tracking (NNT): markers labeled in the previous frame are predicted from their measured velocity (and
   acceleration, once labeled three frames running) and matched one-to-one to points with the Hungarian
   method inside a gate that widens with speed x frame time.
2. Checks: a label its rigid partners disagree with (a swap of two close markers, a ghost caught while the
   marker hid), by more than their distances to it spread, is withdrawn or swapped back; long-run partner
   distances repair what rigid checks miss; two labels that each sit where a recent skeleton fit puts the
   other are swapped back (a mirror-image pair, such as toe and fifth metatarsal, keeps every distance to
   its partners when crossed).
3. Re-acquisition: every occluded marker is predicted, from its *rigid partners* when three of them are
   labeled now (Kabsch on the partners' positions when the marker was last seen, i.e. a rigid-body fill;
   the most accurate prediction there is and free of calibration error), else from the fitted skeleton,
   else by coasting. Remaining points are assigned to these predictions with the Hungarian method inside a
   gate, so ghosts far from any prediction stay unlabeled; labels the skeleton disagrees with by more than
   `reject_residual_m` are withdrawn: a wrong label costs more than a missing one. On a segment none of
   whose markers is labeled (its pose is the fit's guess), markers are taken two or more at once, at the
   model's distances. Markers neither can place, unlabeled a few frames though in view (a hand that moved
   while hidden, where the fit, with nothing to hold it, kept it), and the markers of a segment none of
   whose markers is labeled (a foot back from an occlusion: its partners across the joint place it no
   better than the fit) are first looked for by registering their segment around its joint, where a fit
   at most SEARCH_FIT_AGE_FRAMES old puts it (an older one: a solve is launched and the search waits a
   frame). A marker its partners place where no point is gets a second opinion from a well-fitting
   skeleton (SECOND_OPINION_GATE_M); with no skeleton at all, a cluster hidden whole is found by its own
   layout (`_search_rigid_groups`). A subject with fewer than 4 labels (it left the volume, or was hidden
   whole) is looked for by registering its last marker cloud onto the unclaimed points nearby (rigid
   ICP): on every frame at first, then on every RELOCATE_EVERY_FRAMES-th.
   The periodic work (every 2nd, 3rd, 4th frame) runs on frames chosen by the subject's frame count,
   which starts at its phase (`new_state`), so subjects do it on different frames.
   Here the frame's labels are final. What follows (`step(defer=True)` leaves it to `finish`, after the
   daemon has published them) changes the state, not this frame's labels:
4. Every SHAPE_EVERY_FRAMES frames, labels permuted within a segment (a wrist triad after a fast pass,
   tracked permuted since, which the partner statistics absorb), or a re-acquired label on the point of
   another marker of its segment, are put back where the segment's calibrated marker layout says
   (`_relabel_by_shape`); two labels of a segment whose other markers hide, swapped, are put back by a free
   point and the segment's joint (`_complete_by_free_point`), and a segment's one label on another of its
   markers' points by two free points and the joint (`_complete_lone_label`). The state tracks the new
   labels from the next frame on.
5. The skeleton fit (optimistix Gauss-Newton, `service.solver`) is launched on the frame's final labels when
   a hidden marker is left that rigid partners cannot place, after a relabelling, and at least every
   `max_skip_frames` frames (and `max_skip_s` seconds); otherwise it is skipped. It computes
   asynchronously (XLA's thread) and is collected by the engine for the frame's pose, or at the next frame
   (`collect`), whose skeleton predictions are its markers carried forward at their velocity. The labels
   never wait for a solve; the pose waits only for its own. Markers hidden long are re-acquired inside a
   gate that widens with the time hidden.

Rigid partners are learned online: running statistics of every pairwise marker distance (only over
labeled frames) rank, for each marker, the partners whose distance varies least. They are kept with two
memories, ~100 frames and ~1000 (SLOW_ALPHA): the long one still sees a swap the short one has absorbed.

The loops over markers, partners and relabellings are compiled (`service.kernels`, numba); this module
keeps the decisions, the kernels the arithmetic.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from protocol.skeleton import N_SEGMENTS, PARENTS, SEGMENTS
from service import kernels
from service.config import EngineConfig

N_PARTNERS = 8
#: Partners nearly in a line place a far marker poorly: a turn about the line is left to their skin wobble
#: (3 mm), which the lever swings (`kernels.rigid_predict`); a prediction that could swing more than this
#: [m] does not withdraw a tracked label. A knee, a thigh and a shoulder marker placed a foot marker 17 cm
#: off in one frame, and its correct track was withdrawn (cmu/135_02 at L3).
RIGID_MAX_SWING_M = 0.05
#: A tracked label is withdrawn when farther from its rigid prediction than rigid_check_m (+ 4 x the partners'
#: misfit) + this many times the spread of its partners' distances to it (`_partner_sigma`): partners across
#: a joint learned still in the seed place a serving arm's elbow 9 cm off in one 50 Hz frame while their own
#: distances to it vary by 2-4 cm, and its correct label was withdrawn; a neighbour took its point for 140
#: frames (two players at L2, seed 3). (Dev suite, 8 files x L2/L3 x seeds 0-17: L3 98.01 -> 98.19 %, L2
#: 99.25 -> 99.29 %, 85 runs up, 23 down; at 2 and at 5 L3 moved by under 0.02 from 3, and 5 cost L2 0.02.)
RIGID_LOOSE_K = 3.0
PARTNER_MIN_SAMPLES = 20  # a pair distance sampled fewer times cannot make two markers partners: its
# spread is not known yet (a sternum marker hidden through the seed took two arm markers seen with it in
# 3 frames as its most rigid partners, and was never placed again: squat)
LOOSE_SPREAD_M = 0.015  # partners misfitting more than this hand the prediction to a well-fitting skeleton
SKELETON_TRUSTED_RMS_M = 0.015  # a skeleton fit with a lower RMS residual may predict markers
SECOND_OPINION_GATE_M = 0.03  # ... and re-acquire, within this, those its rigid partners placed where no point was
CROSS_JOINT_DISAGREE_M = 0.12  # a hidden marker whose labeled partners are all on other segments is placed by a
# well-fitting skeleton when they put it farther than this from it; with partners on its own segment,
# farther than SAME_SEGMENT_DISAGREE_M (and it is searched for). (Dev suite, 8 files x L2/L3: from 0.2 to
# 0.14, L3 +0.06 % over seeds 0-11 and +0.12 % over 12-17, unseen while choosing, precision +0.01 / +0.03 %,
# L2 unchanged; at 0.16 a neck marker taken on a head marker's point cost one run 3 % (85_02 at L2), and
# 0.12 cost 0.02 % at L2 over seeds 0-5.)
SAME_SEGMENT_DISAGREE_M = 0.14
MAX_GATE_FACTOR = 1.5  # re-acquisition gate at most this times reacquire_gate_m
# ... and, once a skeleton is fitted, never more than this, however loose the partners and poor the fit:
# a gate that grew with the partners' misfit to 20 cm around a hidden wrist marker took its neighbour's
# point, and kept it (135_02). Without a skeleton the partners are all there is, and the wide gate the
# only way back for a marker whose limb moved while it hid.
MAX_RIGID_GATE_FACTOR = 3.0
HIDDEN_WIDEN_S = 0.5  # a skeleton-predicted marker's gate grows by reacquire_gate_m per this long hidden ...
MAX_HIDDEN_GATE_FACTOR = 2.0  # ... up to this many times reacquire_gate_m
RELOCATE_RADIUS_M = 2.5  # a lost subject is looked for among the unclaimed points this far (horizontally) ...
RELOCATE_MIN_SHARE = 0.3  # ... and found when this share of its markers has a point after registration
RELOCATE_GATE_FACTOR = 0.5  # ... within this times reacquire_gate_m (the rigid parts; limbs moved meanwhile)
#: With a skeleton, when the whole cloud does not register, the trunk's markers alone are (pelvis, abdomen,
#: torso, head: they keep their layout while the limbs move), and the subject is found when this share of
#: them has a point within reacquire_gate_m. Measured on the synthetic performer lost for 1.25 s mid-walk
#: (seed 3): the trunk was found on every frame checked over the next 4 s (10-15 of its 15 markers, median
#: error 1-2 cm), the whole cloud on 1 of 4 (its limbs had moved: 6 of 41 markers within the gate at the
#: true shift).
RELOCATE_TRUNK_SHARE = 0.5
RELOCATE_EAGER_FRAMES = 12  # a lost subject is looked for on each of its first this many frames lost ...
RELOCATE_EVERY_FRAMES = 4  # ... then on every this many frames
TRUNK_SEGMENTS = (0, 1, 2, 3)  # indices in protocol.skeleton.SEGMENTS
#: A pause in a subject's frames longer than this [s] (a stream paused and resumed, a sender that stalled,
#: a daemon thinning a long backlog never leaves one this long) leaves every track stale: the subject moved
#: on meanwhile, and chaining its labels to whatever points lie near where it was labels them wrong for
#: good. It is looked for as a lost subject instead (`_relocate`).
LOST_AFTER_GAP_S = 0.25
SEGMENT_DISTANCE_TOL_M = 0.015  # markers re-found together on an unobserved segment keep the model's distances
LONE_OWN_M = 0.03  # ... and one alone is taken this close to where the fit puts it ...
LONE_OTHERS_M = 0.08  # ... and this far from where it puts the segment's other hidden markers ...
LONE_MAX_DRIFT_M = 0.1  # ... if it hid slowly enough to coast less than this (speed x time hidden)
SEARCH_LOST_FRAMES = 3  # a marker unlabeled this many frames on a segment the fit cannot place is searched for
SEARCH_EVERY_FRAMES = 3  # ... on every 3rd frame, around its segment's joint (`_search_segments`)
#: ... around a fit at most this many frames old, else it waits a frame for one. At 1.5 (a fit of the last
#: frame) a synthetic foot hidden whole mid-walk came back 77 % labeled instead of 98 % (test_engine's foot
#: test), and since `_complete_by_free_point` the dev suite's L3 is lower too (97.61 -> 97.48 %).
SEARCH_FIT_AGE_FRAMES = 3.5
SEARCH_JOINT_TOL_M = 0.03  # a point this close to a marker's distance from its joint may be it ...
SEARCH_PAIR_TOL_M = 0.012  # ... two points this close to the model distance between two of its markers ...
SEARCH_INLIER_M = 0.012  # ... and a marker with a point this close to where the registered segment puts it
#: ... or this close, where three labeled markers of its segment put it: they place it by its layout alone,
#: which skin and joint motion bend (a serving forearm's marker sat 12-21 mm from where the two wrist markers
#: and the finger put it, and stayed unlabeled in view for 34 frames: tennis, two players, at L3)
SEARCH_PLACED_INLIER_M = 0.024
#: A segment whose joint is misplaced too (its parent segment moved unseen: a whole arm swung while the
#: subject was lost) is looked for by its own layout, as a free rigid body whose joint lies this close to
#: its bone's length from the grandparent joint (`_search_free_segment`). The grandparent joint is where the
#: trunk's fit puts it, but a shoulder rides on its shoulder blade, which lifts a raised arm several
#: centimetres: serving forearms placed right had their elbows 6.7-7.7 cm beyond the upper arm's length
#: (two players at L3, a run +0.38 with them). At 8 cm rather than 5, dev suite, 18 realizations: L3 98.360 ->
#: 98.380 %, L2 99.312 -> 99.314 % (tennis L3 +0.07, two players L3 +0.03; one two-player run -1.3: a
#: forearm found mid-serve was lost to its neighbours' points on the next frame, its markers' velocities
#: unknown).
SEARCH_BONE_TOL_M = 0.08
#: ... and, when no triangle with a fourth marker places it, by its triangles one by one: the best placement
#: is taken if no disagreeing one fits about as well within this times the search's tolerances ...
RIVAL_TOL_FACTOR = 2.0
#: ... and if its triangle fits their layout within this RMS. Logged against the truth (dev files at L3,
#: 18 seeds each): with the rival rule alone, 64 placements of three taken right and 4 wrong, the wrong ones
#: at 5.1-6.7 mm and 18 right ones beyond. With this RMS and `_consensus`, on all 8 files: 78 placements
#: taken (50 of three markers, 28 of four or five), 263 labels, 1 wrong; 30 held back as ambiguous
SEARCH_THREE_RMS_M = 0.005
#: With no skeleton (`_search_rigid_groups`), markers whose mutual distances varied less than GROUP_SD_M
#: move as one cluster; its triangle is matched to points at its distances within GROUP_PAIR_TOL_M + 3
#: sigma, its markers are placed on points within GROUP_INLIER_M, and it is taken when GROUP_MIN_PLACED
#: are (a triangle and one more), all within GROUP_REACH_M beyond the reach the distance statistics give
#: from every labeled marker (mean + 4 sigma: a limb swings out of the range it showed)
GROUP_SD_M = 0.005
GROUP_PAIR_TOL_M = 0.004
GROUP_INLIER_M = 0.008
GROUP_MIN_PLACED = 4
GROUP_REACH_M = 0.4
#: A segment with too few markers in view to be placed alone around its joint is placed with its child,
#: unlabeled too, around the joint it puts the child's at: when the two place this many markers
#: (`_down_the_chain`)
CHAIN_MIN_MARKERS = 5  # (counting the segment's labeled markers)
#: ... and so is a segment with this many markers labeled or fewer: one labeled marker and the joint leave
#: it free to turn about them (a shank: its knee marker labeled, its ankle marker lost with the foot)
CHAIN_MAX_LABELED = 1
AGREEING_PAIRS_MAX = 24  # `_agreeing_pairs` weighs at most this many pair hypotheses (typically 1-10)
CHAIN_JOINT_TOL_M = 0.06  # ... the segment's markers within this of their distance from its joint
RIVAL_JOINT_MARGIN_M = 0.05  # a search's points stay unassigned if a rival segment's joint fits within this of its own
SHAPE_EVERY_FRAMES = 4  # segment layouts are checked on every this many frames
SHAPE_LAYOUT_TOL_M = 0.02  # only markers that kept their offset in their segment this well [m] take part ...
SHAPE_MIN_RMS_M = 0.012  # a segment whose labels fit its calibrated marker layout this well is not re-checked ...
SHAPE_FIT_FACTOR = 4.0  # ... nor one fitting it within this times its markers' own layout residual ...
SHAPE_FIT_FLOOR_M = 0.004  # ... (not under this)
SHAPE_GAIN = 0.5  # labels of a segment are permuted when that fits its layout under this times as badly ...
SHAPE_GOOD_RMS_M = 0.015  # ... and as well as true labels do [m] RMS
SHAPE_DISTINCT_M = 0.03  # ... and only relabellings that move the layout's own markers this far [m] RMS ...
# ... or, on clear evidence, one that moves them at least SHAPE_CLEAR_MIN_M: a segment of SHAPE_CLEAR_MIN_LABELS
# labels or more whose layout held within SHAPE_CLEAR_LAYOUT_M in calibration, its labels misfitting by
# SHAPE_CLEAR_SHARE of that move or more, the relabelled ones fitting within SHAPE_CLEAR_FIT_M (or twice the
# layout's residual), and no other relabelling within twice that + 1 mm
SHAPE_CLEAR_MIN_M = 0.006
SHAPE_CLEAR_MIN_LABELS = 3
SHAPE_CLEAR_LAYOUT_M = 0.0025
# ... or within SHAPE_CLEAR_HANDOVER_LAYOUT_M for a relabelling that hands a label to an unlabeled marker (a
# toe label on the fifth metatarsal's point of a foot calibrated to 4 mm: 12-15 mm misfit, 4 mm handed over,
# 85_02 at L2, for 1.5 s; a wrist label on the other wrist marker's point of a forearm calibrated to 4.7 mm:
# 20 mm misfit, 5 mm handed over, 135_02 at L3, for 4 s; among labeled markers alone, a wrist pair 6-11 mm
# apart in a 4 mm layout was swapped wrongly, 135_02 at L3. Dev suite, 18 realizations: at 4.5 mm L3 97.925 %,
# at 6 or 8 mm 97.932 %, six runs moved.)
SHAPE_CLEAR_HANDOVER_LAYOUT_M = 0.006
SHAPE_CLEAR_SHARE = 0.6
SHAPE_CLEAR_FIT_M = 0.002
#: A label tracked all along is handed to an unlabeled marker of its segment (which `relabel_candidates`
#: blocks: it is not suspected of sitting on another's point) where the evidence is overwhelming: a segment
#: of SHAPE_CLEAR_MIN_LABELS labels or more misfitting its layout by this much, and fitting it with the label
#: handed over as tightly as right labels do (its check's tolerance). A wrist label that came back on the
#: forearm marker's point stayed there 2.3 s, 40 mm off the layout, 3 mm handed over (85_12 at L2)
SHAPE_SETTLED_HANDOVER_MISFIT_M = 0.025
# `_reseat_outliers`: a segment with this many labels or more whose labels misfit its layout by this times
# the layout's residual (as `_complete_by_free_point` counts it) ...
RESEAT_MIN_LABELS = 4
RESEAT_MISFIT_FACTOR = 3.0
RESEAT_SHARE = 0.35  # ... and fit it within this share of that misfit (or the residual) with one label left out ...
RESEAT_RADIUS_M = 0.02  # ... has that label moved to a point this close to where the others put it
COMPLETE_FIT_FACTOR = 3.0  # (`_complete_by_free_point`) a labeling whose three points fit the layout within this times its markers' residual ...
COMPLETE_FIT_FLOOR_M = 0.005  # ... or this [m] RMS, whichever is more ...
COMPLETE_JOINT_RMS_M = 0.02  # ... and whose markers and joint fit the offsets this well [m] RMS ...
COMPLETE_PAIR_MISFIT_M = 0.01  # ... is taken, rivalled or not, when the labeled pair's distance misfits the layout's by this much [m] ...
COMPLETE_WRONG_PAIR_JOINT_M = 0.1  # ... and the joint fits within this [m] RMS (the pair is wrong: the joint only guards)
SHAPE_CONFIRM = 2  # ... when the same relabelling wins this many checks running
#: A fit that followed permuted labels takes several solves to turn the segment back once the layout checks
#: have put them right: meanwhile its predictions sit where the old labels were, and the skeleton's unswap
#: would permute them again (a foot's toe and fifth metatarsal, so swapped back, stayed swapped for 12 s:
#: 85_12 at L3). So for this many frames it may not swap them.
SHAPE_HOLD_FRAMES = 8
#: A label carried on by tracking alone since its segment's layout last confirmed it (every layout marker of
#: the segment labeled, SETTLED_MIN_LABELS or more, fitting) is settled: no other marker's point was in its
#: gate since, nor did any step but tracking move it, so nothing could have permuted it, and the layout
#: check leaves it where it is. A forearm twisting under pronation moves its wrist markers against its
#: proximal marker by a centimetre: the true labels misfit the layout by 10 mm where their swap fitted it
#: by 3, and the check swapped two wrist labels tracked apart at 0.1 m/s for 5 s (135_02 at L3, four
#: realizations in 18). (Dev suite, 18 realizations: L3 97.977 -> 98.025 %, L2 99.219 -> 99.225 %, no run
#: lower; settling on any fit of its labels instead held permutations the fit could not see: a wrist label
#: re-acquired on its neighbour's point passes a three-marker forearm's check, 97.967 %. Counting a ghost
#: in the gate as an event too left fewer labels settled at L3: 97.994 %.) A tracked step longer than
#: SLIDE_SHARE of the way to the nearest other label is an event too (without it, 98.021 %: a serving arm's
#: labels slid one marker down the chain with no rival point in any gate, and a two-player run lost 0.6).
SETTLED_MIN_LABELS = 3
SLIDE_SHARE = 0.5
#: (`_mirror_by_joint`) a relabelling the layout cannot tell from the identity (three markers and their mirror
#: image) is taken when, with the segment's joint as a fourth point, it fits under JOINT_GAIN times the
#: identity, which misfits by JOINT_MIN_MISFIT_M or more. (Dev suite: at 0.5, L2 99.215 -> 99.193 %, HDM05 lost up
#: to 0.7 points on four runs; at 0.3, L2 99.227 %, L3 97.630 -> 97.646 %, 91 of 96 runs identical; seeds 6-11: L3
#: 97.361 -> 97.371 %.)
JOINT_GAIN = 0.3
JOINT_MIN_MISFIT_M = 0.015
#: Segments that twist along their length: a forearm carries the wrist and hand markers, which pronation
#: turns about the ulna against its proximal marker, so its layout, rigid in a seed that did not show it,
#: misfits its true labels by ~10 mm, and the wrist pair swapped fits it to 3 mm (the pair is near-mirror
#: symmetric about the forearm's axis). On these a relabelling the layout barely tells (taken on clear
#: evidence) must not fit the joint worse than the labels do (`_relabel_by_shape`). (Dev suite, 18
#: realizations: L2 99.225 -> 99.239 %, L3 98.035 -> 98.056 %, 11 runs up, one down by 0.09; five 135_02 runs
#: at L3 had the right wrist labels swapped for 1-2.5 s. On every segment: L3 98.028 %, a head band's
#: near-square layout, which its joint barely tells, stayed permuted on 85_12, -3.3 points.)
TWISTING_SEGMENTS = (SEGMENTS.index("l_forearm"), SEGMENTS.index("r_forearm"))
#: Segments that bend at their far end: a foot's toe marker sits on the toes, which bend at the metatarsal
#: heads (kneeling, on tiptoe), and the rigid layout does not follow them: 135_02's right toe marker came
#: 5.5 cm nearer the heel for seconds: heel and toe labels misfit the layout by 28 mm RMS, and as heel
#: and fifth metatarsal they fit it at 12 mm. Handing the toe label's point to the metatarsal
#: then fit "better" than the true labels and was taken, for 1-1.7 s each time. On these a relabelling that
#: hands a label to an unlabeled marker must leave the labels fitting the layout as right labels do (the
#: tolerance a check counts as fitting; `_relabel_by_shape`). (Dev suite, 18 realizations: 135_02 at L2
#: 99.70 -> 99.79 %, precision 99.87 -> 99.93 %; L2 99.294 -> 99.304 %, L3 98.351 -> 98.353 %, 11 runs up,
#: 3 down by 0.15 points or less. On every segment, L3 fell to 98.341 %: a tennis wrist's right handover
#: fits its layout at 10-15 mm; on every segment but the forearms, where the layout held within 2.5 mm, a
#: waist label handed over at 11.7 mm was the right one, 85_12 at L3.)
BENDING_SEGMENTS = (SEGMENTS.index("l_foot"), SEGMENTS.index("r_foot"))
SHAPE_FIT_ALPHA = SHAPE_EVERY_FRAMES / 200  # the share of checks (over ~200 frames) on which a segment's labels fit its layout, a running mean ...
SHAPE_TRUSTED_SHARE = 0.3  # ... at least this, over more than SHAPE_MIN_CHECKS checks, for its layout to be trusted
SHAPE_MIN_CHECKS = 5
SHAPE_MAX_JUMP_M = 0.3  # ... and only relabellings that move no label farther than this (heel to toe: ~25 cm) ...
SHAPE_MAX_HANDOVER_M = 0.2  # ... nor hand a label to an unlabeled marker farther than this from where it was
SHAPE_MIN_LABELED = 2  # segments with this many labeled markers are checked (two: their distance, against a spare marker's)
SHAPE_ALL_MAPS = 5  # segments with up to this many labels try every permutation of them, larger ones every swap
PROBATION_FRAMES = 60  # frames a re-acquired label is re-checked against the partners' long-run distances
CHECK_RESIDUAL_M = 0.006  # a tracked label this far [m] (+10 % of the step) from its prediction is checked
CHECK_EVERY_FRAMES = 4  # every tracked label is checked against its rigid partners this often anyway
REPAIR_EVERY_FRAMES = 4  # the long-run distance repair runs on every 4th frame (a swap lives 3 frames more)
Z_SUSPECT = 4.0  # a label whose distances to its most rigid partners stray more sigmas than this is suspect
#: The partner distances are kept twice: a running mean/variance that follows the body within ~100 frames
#: (partners, weights, checks), and one with this smaller weight per update (~1000 frames), which a fresh
#: swap cannot absorb. A wrist label swapped onto a waist marker's point 1.3 cm away had widened the fast
#: statistics' spread enough to look normal within 10 frames, and stayed for 4 s (135_02 at L2); the slow
#: ones still called it 7 sigmas off, and the repair swaps it back.
SLOW_ALPHA = 0.002
MAX_SPEED_M_S = 15.0  # markers never move faster; caps velocities estimated from bad predictions
MAX_ACC_M_S2 = 300.0  # ... nor accelerate faster (a tennis serve's hand reaches ~200 m/s^2)
SKELETON_VELOCITY_GAP_S = 0.05  # two fits at most this far apart give the skeleton markers' velocity
_BIG = kernels.BIG  # a cost or score that must never be chosen
_PARENTS = np.asarray(PARENTS, np.int64)


def _norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (np.linalg.norm costs several times more on these small arrays)."""
    return np.sqrt(np.einsum("...i,...i->...", v, v))


@dataclasses.dataclass(frozen=True)
class SubjectModel:
    """A subject's calibration: its markers and, when known, its skeleton."""

    name: str
    markers: tuple[str, ...]
    marker_segment: np.ndarray  # (M,) int, segment index of each marker (-1 until the skeleton is calibrated)
    marker_offsets_m: np.ndarray  # (M, 3) offset in the segment frame
    joint_offsets_m: np.ndarray  # (14, 3) segment origin in the parent frame
    has_skeleton: bool = False
    # The segments' marker layouts as first calibrated (from given labels, in seeded mode), which the
    # tracker checks labels against (`_relabel_by_shape`): refinements on the engine's own labels move
    # marker_offsets_m, never these. (M, 3) offsets, and (M,) how well each marker kept its offset over
    # the calibration frames [m] (`calibration.layout_residuals`); None = not measured.
    layout_offsets_m: np.ndarray | None = None
    layout_rms_m: np.ndarray | None = None

    @property
    def n_markers(self) -> int:
        return len(self.markers)

    @functools.cached_property
    def layout_joints_m(self) -> np.ndarray:
        """(N_SEGMENTS, 3) where each segment's joint, as the model has it now, lies in its calibrated layout
        (zeros without a measured layout). Refinement moves the joints and the offsets, keeping the
        segments' rotations, but not the layout: the searches and checks that hang a layout from a joint
        hang it here, not at the layout's own origin (the joint as calibrated). There, a serving forearm
        whose elbow refinement had moved 66 mm had its joint 5.5 cm off the upper arm's length from the
        shoulder, and stayed unlabeled in view for 45 frames (two players at L2). The rigid motion taking
        the model's offsets onto the layout places it: refinement reshapes a segment a little too (a head's
        back markers moved 5 cm more than its front ones, 85_12), and the mean shift of its markers
        then put a head's joint where its mirror image fitted better."""
        out = np.zeros((N_SEGMENTS, 3))
        if self.layout_rms_m is None or len(self.layout_rms_m) != self.n_markers:
            return out
        measured = (self.layout_rms_m < SHAPE_LAYOUT_TOL_M) & (self.marker_segment >= 0)
        for k in np.unique(self.marker_segment[measured]):
            rows = measured & (self.marker_segment == k)
            if rows.sum() >= 3:
                out[k] = rigid_motion(self.marker_offsets_m[rows], self.layout_offsets_m[rows])[1]
            else:  # (two markers: no rotation to take out)
                out[k] = np.mean(self.layout_offsets_m[rows] - self.marker_offsets_m[rows], axis=0)
        return out


@dataclasses.dataclass
class TrackState:
    """Everything that changes frame to frame for one subject (owned by the engine's registry)."""

    pos_m: np.ndarray  # (M, 3) last observed or predicted position
    vel_m_s: np.ndarray  # (M, 3)
    labeled: np.ndarray  # (M,) bool, labeled in the last processed frame
    ever_seen: np.ndarray  # (M,) bool
    last_t_ns: int
    # rigid-partner memory
    dist_n: np.ndarray  # (M, M) samples in the running distance statistics
    dist_mean_m: np.ndarray  # (M, M)
    dist_var_m2: np.ndarray  # (M, M)
    dist_slow_mean_m: np.ndarray  # (M, M) the same, with a long memory (SLOW_ALPHA)
    dist_slow_var_m2: np.ndarray  # (M, M)
    partners: np.ndarray  # (M, K) int, -1 = none
    snap_m: np.ndarray  # (M, M, 3): row i = every marker's position when i was last labeled (NaN = unlabeled then)
    snap_kept_m: np.ndarray  # (M, M, 3): row i of snap_m as it was before i's label was re-acquired (off probation)
    provisional: np.ndarray  # (M,) int, frames left in which a re-acquired label is re-checked
    # skeleton
    t_root_m: np.ndarray  # (3,)
    R_parent_segment: np.ndarray  # (14, 3, 3)
    skipped: int = 0  # solves skipped in a row
    frames: int = 0  # frames processed, counted from the subject's phase (`new_state`)
    search_waits: bool = False  # a segment search waits for the solve launched on the last frame
    lost_frames: int = 0  # frames running on which the subject was lost (fewer than 4 labels after tracking)
    last_labeled_t_ns: int = 0
    fit_rms_m: float = float("nan")  # of the latest completed fit
    fit_iterations: int = 0  # of the latest completed fit
    # the fit launched on a frame's final labels, (PendingFit, t_ns), collected at the next frame (`collect`)
    pending: tuple | None = None
    # a frame's bookkeeping (the layout check, the state update, the solve launch) that `step(defer=True)`
    # left for after its labels were published; `finish` runs it, and so does anything that reads the
    # state (`collect`)
    unfinished: object | None = None
    skel_pred_m: np.ndarray | None = None  # (M, 3) marker positions of the latest completed fit ...
    skel_vel_m_s: np.ndarray | None = None  # (M, 3) ... their velocity (from the fit before it) ...
    skel_t_ns: int = 0  # ... and the time of the frame it fitted
    acc_m_s2: np.ndarray | None = None  # (M, 3) from two measured velocities (labeled 3 frames running), else 0
    vel_measured: np.ndarray | None = None  # (M,) bool: vel_m_s comes from two observations
    acc_dt_s: float = 0.0  # the frame interval acc_m_s2 was measured over
    hidden_frames: np.ndarray | None = None  # (M,) int: frames since the marker was last labeled
    layout_hold: np.ndarray | None = None  # (M,) int: frames left in which the skeleton may not swap labels the layout checks moved
    settled: np.ndarray | None = None  # (M,) bool: the label is beyond the layout check's doubt (SETTLED_MIN_LABELS)
    # the layout check (`_relabel_by_shape`): per segment, the relabelling asked for on the last checks
    # and on how many checks running; per set of labeled markers (bytes), the RMS of each of its
    # relabellings of the layout onto itself; per segment, the share of checks on which the labels or a
    # permutation of them fitted the layout, and how many checks there were
    shape_votes: dict = dataclasses.field(default_factory=dict)
    shape_symmetry: dict = dataclasses.field(default_factory=dict)
    shape_fit: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(N_SEGMENTS))
    shape_checks: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(N_SEGMENTS))
    # `_complete_by_free_point`: per segment, the relabelling asked for on the last checks, and how many running
    complete_votes: dict = dataclasses.field(default_factory=dict)
    # `_reseat_outliers`: per marker, the point owner (marker, -1 = a free point) proposed on the last checks, and how many running
    reseat_votes: dict = dataclasses.field(default_factory=dict)
    # `_joints_m`: the segment origins of the pose (t_root_m, R_parent_segment, joint offsets) they were computed for
    joints_cache: tuple | None = None


@dataclasses.dataclass(frozen=True)
class StepResult:
    point_index: np.ndarray  # (M,) int32, -1 = not observed
    predicted_m: np.ndarray  # (M, 3)
    solved: bool
    iterations: int
    residual_m: float
    source: np.ndarray | None = None  # (M,) int8 per marker: 0 none, 1 tracked (NNT), 2 re-acquired, 3 given
    positions_m: np.ndarray | None = None  # (M, 3) position of the point each marker is labeled with, NaN = none


def new_state(model: SubjectModel, positions_m: np.ndarray, t_ns: int, history_m: np.ndarray | None = None,
              phase: int = 0) -> TrackState:
    """Start tracking from known marker positions (M, 3; NaN = unseen), with optional labeled history
    (F, M, 3) to seed the rigid-partner statistics. The frame count starts at `phase`: the periodic work
    (layout checks, searches, repairs, full rigid checks) runs on frames chosen by that count, so subjects
    given different phases do it on different frames instead of all on the same one (8 subjects started
    together: a 28 ms frame every 4th, against 9 ms mean)."""
    m = model.n_markers
    seen = np.isfinite(positions_m[:, 0])
    st = TrackState(
        pos_m=np.where(seen[:, None], positions_m, 0.0),
        vel_m_s=np.zeros((m, 3)),
        labeled=seen.copy(),
        ever_seen=seen.copy(),
        last_t_ns=t_ns,
        dist_n=np.zeros((m, m)),
        dist_mean_m=np.zeros((m, m)),
        dist_var_m2=np.zeros((m, m)),
        dist_slow_mean_m=np.zeros((m, m)),
        dist_slow_var_m2=np.zeros((m, m)),
        partners=np.full((m, N_PARTNERS), -1),
        snap_m=np.full((m, m, 3), np.nan),
        snap_kept_m=np.full((m, m, 3), np.nan),
        provisional=np.zeros(m, int),
        t_root_m=np.zeros(3),
        R_parent_segment=np.tile(np.eye(3), (14, 1, 1)),
        last_labeled_t_ns=t_ns,
        acc_m_s2=np.zeros((m, 3)),
        vel_measured=np.zeros(m, bool),
        hidden_frames=np.zeros(m, int),
        layout_hold=np.zeros(m, int),
        settled=np.zeros(m, bool),
        frames=phase,
    )
    if history_m is not None:
        for frame in history_m:
            _update_distances(st, frame, np.isfinite(frame[:, 0]), alpha_min=0.0)
        _update_partners(st)
        # replay the history so every marker remembers where it and the others were when it was last seen
        for frame in history_m:
            ok = np.isfinite(frame[:, 0])
            _snapshot(st, frame, ok)
            st.pos_m[ok] = frame[ok]
            st.ever_seen |= ok
    else:
        _update_partners(st)
    _snapshot(st, np.where(seen[:, None], positions_m, np.nan), seen)
    st.pos_m[seen] = positions_m[seen]
    return st


def _update_distances(st: TrackState, pos: np.ndarray, labeled: np.ndarray, alpha_min: float = 0.02) -> None:
    """Running mean/variance of pairwise distances among labeled markers (count-based, then EMA with weight
    alpha_min, and with SLOW_ALPHA for the long-memory pair), in place. (A compiled loop: `kernels`.)"""
    if np.count_nonzero(labeled) >= 2:
        kernels.update_distances(st.dist_n, st.dist_mean_m, st.dist_var_m2, st.dist_slow_mean_m, st.dist_slow_var_m2,
                                 pos, labeled, alpha_min, min(alpha_min, SLOW_ALPHA))


def _update_partners(st: TrackState) -> None:
    """For every marker, the K partners whose distance to it varies least (ties broken by nearness)."""
    m = len(st.pos_m)
    score = np.sqrt(st.dist_var_m2) + 0.02 * st.dist_mean_m
    score = np.where(st.dist_n >= PARTNER_MIN_SAMPLES, score, _BIG)
    np.fill_diagonal(score, _BIG)
    k = max(min(N_PARTNERS, m - 1), 0)  # (a subject of one marker has no partner)
    order = np.argsort(score, axis=1)[:, :k]
    ok = np.take_along_axis(score, order, axis=1) < _BIG
    partners = np.full((m, N_PARTNERS), -1)
    partners[:, :k] = np.where(ok, order, -1)
    st.partners = partners


def _snapshot(st: TrackState, pos: np.ndarray, labeled: np.ndarray) -> None:
    """Remember, for each labeled marker, where every labeled marker is now. Keeping all of them (not only
    the current partners) lets the partner lists change while a marker is hidden."""
    kernels.snapshot(st.snap_m, pos, labeled)


def rigid_predictions(st: TrackState, pos: np.ndarray, labeled: np.ndarray, which: np.ndarray):
    """Predict markers `which` from their rigid partners labeled now (`pos`, NaN elsewhere).

    For each marker, the partners' positions when it was last seen are carried onto their positions now by
    the best rigid transform (weighted Kabsch), and so is the marker. Partners are weighted by how rigidly
    they keep their distance to it (sigma + 3 mm of skin). Returns (pred (M, 3), spread (M,) = weighted
    RMS misfit of the partners [m], swing (M,) = how far [m] their skin wobble could turn it about their long
    axis); NaN where fewer than 3 usable partners. (A compiled loop: `kernels`.)
    """
    return kernels.rigid_predict(st.partners, st.snap_m, st.dist_var_m2, pos, labeled, which)


def _partner_sigma(st: TrackState, labeled: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """How loosely the labeled partners of markers `rows` hold them (R,) [m]: the spread of their distances to
    it, averaged with `rigid_predict`'s weights (1 / (sigma + 3 mm)^2, so the tightest partners count most).
    Three partners always fit their own snapshot closely, whatever the spread of their distances to the
    marker (`spread` says nothing then); this says how far from their prediction the marker may be."""
    part = st.partners[rows]
    ok = (part >= 0) & labeled[np.maximum(part, 0)]
    sd = np.sqrt(st.dist_var_m2[rows[:, None], np.maximum(part, 0)])
    w = np.where(ok, 1.0 / (sd + kernels.SKIN_M) ** 2, 0.0)
    return np.sqrt(np.sum(w * sd**2, axis=1) / np.maximum(np.sum(w, axis=1), 1e-12))


def _distance_stats(st: TrackState, slow: bool) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance) (M, M) of the partner distances: the long-memory pair if `slow`, else the running one."""
    return (st.dist_slow_mean_m, st.dist_slow_var_m2) if slow else (st.dist_mean_m, st.dist_var_m2)


def distance_misfit(st: TrackState, cur: np.ndarray, labeled: np.ndarray, rows: np.ndarray | None = None,
                    slow: bool = False) -> np.ndarray:
    """How many standard deviations each labeled marker's distances to its most rigid labeled partners
    stray from their long-run means: the median z = |d - mean| / (sigma + 3 mm) over (up to) the 3
    partners with the smallest sigma that are labeled now. Unlike the rigid prediction, which follows the
    last frames, this remembers the body, so a wrong label cannot become its own reference; `slow` takes
    the long-memory statistics. NaN for markers with fewer than 2 such partners."""
    mean, var = _distance_stats(st, slow)
    idx = np.arange(len(cur)) if rows is None else np.asarray(rows, dtype=np.int64)
    return kernels.distance_misfit(st.partners, st.dist_n, mean, var, cur, labeled, idx)


def _misfit_at(st: TrackState, i: int, x: np.ndarray, cur: np.ndarray, labeled: np.ndarray, exclude: int = -1,
               slow: bool = False) -> float:
    """distance_misfit of marker i if it were at x (NaN with fewer than 2 usable partners)."""
    part = st.partners[i]
    part = part[(part >= 0) & (part != exclude)]
    part = part[labeled[part] & (st.dist_n[i, part] >= 10)]
    if len(part) < 2:
        return float("nan")
    mean, var = _distance_stats(st, slow)
    sigma = np.sqrt(var[i, part]) + 0.003
    best = np.argsort(sigma)[:3]
    z = np.abs(np.linalg.norm(cur[part[best]] - x, axis=1) - mean[i, part[best]]) / sigma[best]
    return float(np.median(z))


def _repair_by_distances(
    st: TrackState, point_index: np.ndarray, cur: np.ndarray, points: np.ndarray, free: np.ndarray
) -> None:
    """Where the long-run partner distances say a label is wrong (z > Z_SUSPECT), move it: swap two close
    suspects when each fits where the other is, or take a free point nearby that fits far better (the
    freed point's own marker can then re-acquire it). Catches swaps that rigid checks miss because both
    markers moved together since. Judged on the long-memory statistics first (a swap the running ones
    have absorbed), then on the running ones. In place."""
    for slow in (True, False):
        labeled = point_index >= 0
        z = distance_misfit(st, cur, labeled, slow=slow)
        sus = np.flatnonzero(z > Z_SUSPECT)  # (labeled ones: NaN for the others, and NaN compares False)
        if len(sus) == 0:
            continue
        free_idx = np.flatnonzero(free)
        for a, i in enumerate(sus):
            if point_index[i] < 0 or _swap_back(st, point_index, cur, labeled, z, i, sus[a + 1 :], slow):
                continue
            near = free_idx[np.linalg.norm(points[free_idx] - cur[i], axis=1) < 0.15] if len(free_idx) else free_idx
            if len(near):
                z_near = np.array([_misfit_at(st, i, points[p], cur, labeled, slow=slow) for p in near])
                j = int(np.nanargmin(z_near)) if np.isfinite(z_near).any() else -1
                if j >= 0 and z_near[j] < Z_SUSPECT and z_near[j] < 0.3 * z[i]:
                    free[point_index[i]] = True
                    free[near[j]] = False
                    free_idx = np.flatnonzero(free)
                    point_index[i] = near[j]
                    cur[i] = points[near[j]]


def _swap_back(st: TrackState, point_index: np.ndarray, cur: np.ndarray, labeled: np.ndarray, z: np.ndarray, i: int,
               others: np.ndarray, slow: bool) -> bool:
    """Swap suspect i's label with the first of the suspects `others` within 25 cm such that each fits
    where the other is (their misfits, z, fall under 0.3 of the sum); in place. Whether it swapped."""
    for k in others:
        if point_index[k] < 0 or np.linalg.norm(cur[i] - cur[k]) > 0.25:
            continue
        swapped = _misfit_at(st, i, cur[k], cur, labeled, exclude=k, slow=slow) + _misfit_at(st, k, cur[i], cur, labeled, exclude=i, slow=slow)
        if swapped < 0.3 * (z[i] + z[k]):
            point_index[i], point_index[k] = point_index[k], point_index[i]
            cur[[i, k]] = cur[[k, i]]
            z[i] = z[k] = 0.0
            return True
    return False


def _gather(points: np.ndarray, point_index: np.ndarray) -> np.ndarray:
    """(M, 3) positions of the points each marker is labeled with, NaN where unlabeled (safe for N = 0)."""
    out = np.full((len(point_index), 3), np.nan)
    ok = point_index >= 0
    out[ok] = points[point_index[ok]]
    return out


def _unswap(point_index: np.ndarray, cur: np.ndarray, pred: np.ndarray, err: np.ndarray, tol_m: float) -> bool:
    """Swap the labels of two markers when each sits where the other is predicted (markers that passed
    close to each other and were tracked through crossed): crossed distances under half the straight
    ones, the best pairs first (a poor fit can make a dozen suspects). `err`: each labeled marker's
    distance to its prediction, 0 for the others. In place; True if any pair was swapped. (A compiled
    loop: `kernels.unswap`.)"""
    return kernels.unswap(point_index, cur, pred, err, tol_m)


def _unsure_on_unseen_segment(model: SubjectModel, labeled: np.ndarray, rows: np.ndarray, cur: np.ndarray,
                              use_skel: np.ndarray, seen: np.ndarray, skel_pred: np.ndarray | None,
                              drift: np.ndarray | None = None) -> np.ndarray:
    """Which re-acquisitions (rows, just assigned at positions cur) to hold back: those the skeleton
    predicted on a segment none of whose markers is labeled. Such a segment's pose is the fit's guess (a
    foot hidden while the leg moved), and one point near it could be any of its markers (`seen`: ever
    seen): its markers are taken only two or more at once, at the distances the model puts between them
    (within SEGMENT_DISTANCE_TOL_M), or one alone where the fit puts it within LONE_OWN_M and every other
    hidden marker of the segment farther than LONE_OTHERS_M (dev suite, seeds 0-2: of the lone points so
    held back, 520 such were the marker's and 16 not; 1122 and 159 in all), unless it hid moving: `drift`
    (M,), its speed as the state carries it (decaying while hidden) times the time hidden, at
    LONE_MAX_DRIFT_M or more. The fit holds an unseen segment where it was, so a fast limb is elsewhere by
    then (two players at L3, seed 3: a serving forearm 7 frames hidden, still at 1.4 m/s, predicted 10 cm
    off its point; the other hand's point lay 2 cm from the prediction, and that arm's labels took the
    other's points for 240 frames; dev suite, seeds 0-5, L2 and L3: of 193 lone points so taken, that one
    and 2 right ones moved this far)."""
    hold = np.zeros(len(rows), bool)
    seg = model.marker_segment
    observed = np.zeros(int(seg.max()) + 1, bool)
    observed[seg[labeled]] = True
    guess = use_skel[rows] & ~observed[seg[rows]]
    for k in np.unique(seg[rows[guess]]):
        group = np.flatnonzero(guess & (seg[rows] == k))
        if len(group) < 2:
            # ambiguous only if the segment carries other markers it could be (a lone shin marker is not),
            # and the point is not clearly the one where the fit puts it
            i = rows[group[0]]
            others = np.flatnonzero((seg == k) & seen & ~labeled)
            others = others[others != i]
            clear = (len(others) > 0 and _norm(cur[i] - skel_pred[i]) < LONE_OWN_M
                     and _norm(skel_pred[others] - cur[i]).min() > LONE_OTHERS_M
                     and (drift is None or drift[i] < LONE_MAX_DRIFT_M))
            hold[group] = np.count_nonzero(seen[seg == k]) >= 2 and not clear
            continue
        i = rows[group]
        d_pts = _norm(cur[i][:, None] - cur[i][None])
        off = model.marker_offsets_m[i]
        d_model = _norm(off[:, None] - off[None])
        if np.abs(d_pts - d_model).max() > SEGMENT_DISTANCE_TOL_M:
            hold[group] = True
    return hold


def _relocate(st: TrackState, points: np.ndarray, cand: np.ndarray, gate_m: float, share: float = RELOCATE_MIN_SHARE,
              rows: np.ndarray | None = None) -> np.ndarray | None:
    """Where a lost subject's markers are now (M, 3; NaN = unknown), or None: its last known marker cloud
    (of markers `rows`, default all) registered onto the unclaimed points within RELOCATE_RADIUS_M of it
    by rigid ICP (from four headings, as it may come back turned; at its height: people walk), accepted
    when at least `share` of those markers (and 4) then have a point within `gate_m`. Limbs that moved
    while it was away fit loosely; the torso and head carry the registration, and the skeleton fit finds
    the rest. Runs only while a subject is lost."""
    usable = st.ever_seen & np.isfinite(st.pos_m[:, 0])
    known = np.flatnonzero(usable if rows is None else usable & rows)
    pts = points[cand]
    if len(known) < 4 or len(pts) < 4:
        return None
    src = st.pos_m[known]
    center = src.mean(0)
    for _ in range(3):  # the centre of the unclaimed points around it (mean shift, horizontally)
        near = pts[_norm(pts[:, :2] - center[:2]) < RELOCATE_RADIUS_M]
        if len(near) < 4:
            return None
        center[:2] = near[:, :2].mean(0)
    tree = cKDTree(near)
    need = max(4, int(np.ceil(share * len(known))))
    best, best_n = None, need - 1
    c_src = src.mean(0)
    for yaw in np.arange(4) * (np.pi / 2):
        c, s_ = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        t = center - c_src @ R.T
        pairs = None
        for it in range(12):  # ICP, trimmed: pairs farther than a shrinking radius are left out
            X = src @ R.T + t
            d, j = tree.query(X)
            radius = max(0.3 * 0.7**it, gate_m)
            inl = d < radius
            if inl.sum() < 3:
                break
            if radius == gate_m:  # the radius has stopped shrinking: the same pairs give the same motion again
                now = np.where(inl, j, -1)
                if pairs is not None and np.array_equal(pairs, now):
                    break
                pairs = now
            R, t = rigid_motion(src[inl], near[j[inl]])
        X = src @ R.T + t
        n = int((tree.query(X)[0] < gate_m).sum())
        if n > best_n:
            best, best_n = X, n
    if best is None:
        return None
    out = np.full(st.pos_m.shape, np.nan)
    out[known] = best
    return out


def rigid_motion(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`calibration.rigid_motion`, compiled (`kernels.rigid_motion`): the searches make hundreds a frame."""
    return kernels.rigid_motion(np.require(a, np.float64, "CW"), np.require(b, np.float64, "CW"))


def _joints_m(model: SubjectModel, st: TrackState) -> np.ndarray:
    """World positions (14, 3) of the segment origins in the current pose. Kept until the pose changes (a
    fit is collected: new arrays, never changed in place), since the searches ask several times a frame."""
    pose = (st.t_root_m, st.R_parent_segment, model.joint_offsets_m)
    c = st.joints_cache
    if c is None or any(a is not b for a, b in zip(c[:3], pose)):
        # (a fit's arrays come read-only from XLA: copies, so the kernel sees one type and compiles once)
        c = st.joints_cache = (*pose, kernels.world_transforms(*(np.require(a, np.float64, "CW") for a in pose), _PARENTS)[1])
    return c[3]


def _observed_segments(marker_segment: np.ndarray, labeled: np.ndarray) -> np.ndarray:
    """(N_SEGMENTS,) bool: segments with at least one labeled marker."""
    observed = np.zeros(N_SEGMENTS, bool)
    observed[marker_segment[labeled & (marker_segment >= 0)]] = True
    return observed


def _search_segments(model: SubjectModel, st: TrackState, points: np.ndarray, cand: np.ndarray,
                     labeled: np.ndarray, cur: np.ndarray, lost: np.ndarray) -> dict[int, int]:
    """Which points markers `lost` (labeled on none of the last SEARCH_LOST_FRAMES frames though their segment
    should be in view) are now, {marker: point}. Their segment is registered onto the unclaimed
    points around its joint. The fit has no word on a segment none of whose markers is labeled (it keeps
    it where it was: a wrist flicked while hidden is found tens of centimetres from there), but the joint
    it hangs from is held by the parent. So: a point may be marker i if its distance from the joint matches
    |offset_i| (rotation-invariant); two such points, a pair if their distance matches the model's; the
    segment's rigid motion (Kabsch) from the joint, its labeled markers and the pair places every other
    marker, and the hypothesis placing most markers on points wins, if no other assignment does as well
    (two mirror-image markers alone stay unfound). It must place three markers, labeled ones counted
    (one lost marker of a segment with two labeled is placed where they and the joint put it). A segment
    with too few markers in view to be placed is placed with its child (`_down_the_chain`), failing that,
    if it has two markers, by both (a thigh's knee marker at its distances from the hip and from the thigh
    marker: the fit turns a thigh held by one marker about the hip, and its knee, shank and foot with it);
    one whose joint cannot pin it, by its layout alone (`_search_free_segment`)."""
    found: dict[int, int] = {}
    pw = _joints_m(model, st)
    observed = _observed_segments(model.marker_segment, labeled)
    pool = np.flatnonzero(cand)
    if len(pool) == 0:
        return found
    seg_of = model.marker_segment
    searched = np.flatnonzero(np.bincount(seg_of[lost & (seg_of >= 0)], minlength=N_SEGMENTS))  # (np.unique: 5x the time)
    unfound = lost.copy()
    for k in searched:
        idx = np.flatnonzero((seg_of == k) & st.ever_seen)
        lab, los = idx[labeled[idx]], idx[unfound[idx]]
        if len(los) == 0:
            continue  # found with its parent (`_down_the_chain`)
        scored = _around_joint(model, pw[k], lab, los, cur, points, pool)
        assignment, below = _unambiguous(scored, 0, max(3 - len(lab), 1)), {}
        if assignment is None and len(lab) <= CHAIN_MAX_LABELED:
            assignment, below = _down_the_chain(model, st, k, labeled, lost, cur, points, pool)
        if assignment is None and len(idx) == 2:  # a segment of two: both its markers placed
            assignment = _unambiguous(scored, 0, max(len(idx) - len(lab), 1))
        if assignment is None and len(lab) == 0:
            assignment = _agreeing_pairs(scored)
        if assignment is None and len(lab) == 0:
            # the joint could not pin it (its parent moved unseen too, so the joint is where the fit left
            # it: a serving arm's forearm stayed unfound for 0.7 s): its layout alone
            assignment = _search_free_segment(model, pw, points, pool, los, k, observed)
        if assignment and _rival_fits(model, pw, points, assignment, k, searched):
            assignment = None
        if assignment:
            found.update(assignment)
            found.update(below)
            unfound[list(found)] = False
            pool = pool[~np.isin(pool, list(found.values()))]
    return found


def _agreeing_pairs(scored: list) -> dict[int, int] | None:
    """Markers of a segment none of whose markers is labeled that fit around its joint two at a time but
    not three at once (a serving hand flexed at the wrist moves the finger marker off its forearm layout by
    a few centimetres): three or more points every pair of which is a hypothesis of `scored` (n placed,
    RMS, {marker: point}, ...), if no other such set places as many. {marker: point}, or None. (Two players
    at L2, seed 3: the forearm's finger, wrist and forearm markers were in view 12 frames, each pair
    placed alike, and stayed unfound. Dev suite, 18 realizations: 13 runs moved, 12 up; L3 98.536 ->
    98.540 %, L2 unchanged at 99.324 %.)"""
    # (the search is quadratic in the pairs: the best-fitting few only, as a crowded frame's hundreds
    # would cost milliseconds)
    best_first = sorted((h for h in scored if h[0] == 2 and len(h[2]) == 2), key=lambda h: h[1])
    pairs = [h[2] for h in best_first[:AGREEING_PAIRS_MAX]]
    have = {frozenset(a.items()) for a in pairs}
    sets = set()
    for seed in pairs:
        merged = dict(seed)
        for q in pairs:
            new = [(i, p) for i, p in q.items() if i not in merged]
            if len(new) == 1 and _agrees(merged, q) and all(
                    frozenset({new[0], (j, pj)}) in have for j, pj in merged.items()):
                merged[new[0][0]] = new[0][1]
        if len(merged) >= 3:
            sets.add(frozenset(merged.items()))
    if not sets:
        return None
    most = max(len(x) for x in sets)
    best = [x for x in sets if len(x) == most]
    return dict(best[0]) if len(best) == 1 else None


def _around_joint(model: SubjectModel, o: np.ndarray, lab: np.ndarray, los: np.ndarray, cur: np.ndarray,
                  points: np.ndarray, pool: np.ndarray, refine: bool = False, tol_m: float = SEARCH_JOINT_TOL_M) -> list:
    """Hypotheses (n placed, RMS, {marker: point}, R, t) for a segment whose joint is at `o`, labeled
    markers `lab` (at `cur`) and lost ones `los`, among points `pool`: (R, t) its rigid motion."""
    off = model.marker_offsets_m
    reach = _norm(points[pool] - o)
    within = reach < _norm(off[np.concatenate([lab, los])]).max() + tol_m
    near, r_near = pool[within], reach[within]
    options = {i: near[np.abs(r_near - _norm(off[i])) < tol_m] for i in los}
    base_a = np.vstack([np.zeros((1, 3)), off[lab]])
    base_b = np.vstack([o[None], cur[lab]])
    hyps = []
    if len(lab) >= 2:
        # the joint and two labeled markers fix the segment, three labeled markers alone better (the joint
        # is where the fit puts it, within its residual): one point where they put a lost marker is it
        R, t = rigid_motion(base_a[1:], base_b[1:]) if len(lab) >= 3 else rigid_motion(base_a, base_b)
        at = off[los] @ R.T + t
        gate = SEARCH_PLACED_INLIER_M if len(lab) >= 3 else SEARCH_INLIER_M
        # Three labeled markers place it alone, wherever the fit left the joint: a point's distance from that
        # joint is no test then (a fit at 35-45 mm RMS put a serving elbow 6-15 cm from where the wrist
        # marker's distance from it said, and the marker, 10-14 mm from where its three partners put it,
        # stayed unlabeled in view for 20 frames, two players at L2). Nor is the joint registered with them.
        # (Dev suite, 18 realizations: L2 99.316 -> 99.320 %, L3 98.405 -> 98.410 %, 18 runs up, 3 down by
        # 0.05 points at most.)
        # (each lost marker's candidates at once: point by point, the whole pool with three labeled markers,
        # took 1-2 ms a segment with several subjects' points unclaimed)
        for r, i in enumerate(los):
            cands = pool if len(lab) >= 3 else options[i]
            hyps += [((i, p),) for p in cands[_norm(points[cands] - at[r]) < gate]]
    elif len(lab):  # one point with the joint and a labeled marker already fixes the segment
        hyps += [((i, p),) for i in los for p in options[i]]
    for a, i in enumerate(los):
        for j in los[a + 1 :]:
            d_model = _norm(off[i] - off[j])
            for p in options[i]:
                for q in options[j]:
                    if p != q and abs(_norm(points[p] - points[q]) - d_model) < SEARCH_PAIR_TOL_M:
                        hyps.append(((i, p), (j, q)))
    if not hyps:
        return []
    # (every hypothesis registered and its other markers placed in one compiled call: one by one, each
    # cost ~60 us of numpy calls, and a frame of eight subjects offered a lost forearm hundreds)
    mk = np.full((len(hyps), 2), -1, np.int64)
    pt = np.full((len(hyps), 2), -1, np.int64)
    for r, h in enumerate(hyps):
        for c, (i, p) in enumerate(h):
            mk[r, c], pt[r, c] = i, p
    keep, rms_of, Rs, ts, placed = kernels.joint_hypotheses(
        *(np.require(a, np.float64, "C") for a in (base_a, base_b, off, points)), mk, pt,
        *(np.require(a, np.int64, "C") for a in (los, pool, near)), len(lab) >= 3, float(tol_m), SEARCH_INLIER_M)
    scored = []
    for r in np.flatnonzero(keep):
        assignment = {int(los[c]): int(placed[r, c]) for c in np.flatnonzero(placed[r] >= 0)}
        assignment.update({int(i): int(p) for i, p in hyps[r]})
        if len(set(assignment.values())) < len(assignment):
            continue
        rms, R, t = float(rms_of[r]), Rs[r], ts[r]
        if refine and len(assignment) >= 3:
            # the joint is only roughly where the parent's placement put it: the markers placed, alone, place
            # the segment again
            mk, pt = list(assignment), list(assignment.values())
            R, t = rigid_motion(off[mk], points[pt])
            assignment = _placed(off, los, R, t, points, near)
            if len(assignment) < 3 or len(set(assignment.values())) < len(assignment):
                continue
            mk, pt = list(assignment), list(assignment.values())
            rms = float(np.sqrt(np.mean(np.sum((off[mk] @ R.T + t - points[pt]) ** 2, 1))))
        scored.append((len(assignment), rms, assignment, R, t))
    return scored


def _down_the_chain(model: SubjectModel, st: TrackState, k: int, labeled: np.ndarray,
                    lost: np.ndarray, cur: np.ndarray, points: np.ndarray, pool: np.ndarray
                    ) -> tuple[dict[int, int] | None, dict[int, int]]:
    """Segment k, at most CHAIN_MAX_LABELED of whose markers are labeled, placed with its child: (k's
    {marker: point}, the child's). Its joint is held but too few of its markers are in view to tell one
    placement from another (an upper arm of two markers; a shank whose knee marker alone is labeled);
    each placement puts the child's joint (the elbow, the ankle), around which the child, unlabeled, is
    searched. The combination placing most markers wins if no other does about as well. (After a tennis
    serve a whole arm of six markers stayed unlabeled for 20 frames, in view: both segments unobserved,
    the fit had left the elbow 15-30 cm off. A foot back from an occlusion stayed unlabeled in view under
    a shank with one marker labeled, HDM05 at L3.)"""
    seg_of = model.marker_segment
    mine_idx = np.flatnonzero((seg_of == k) & st.ever_seen)
    mine_lab = mine_idx[labeled[mine_idx]]
    scored = None
    for c in np.flatnonzero(_PARENTS == k):
        idx = np.flatnonzero((seg_of == c) & st.ever_seen)
        los = idx[lost[idx]]
        if len(los) < 2 or labeled[idx].any():
            continue
        if scored is None:
            # the joint may be off by more than a search around it allows (a shoulder raised overhead in a
            # serve slides against the trunk markers that hold it): k is placed within a wider reach, and
            # the child confirms
            scored = _around_joint(model, _joints_m(model, st)[k], mine_lab, mine_idx[lost[mine_idx]], cur,
                                   points, pool, tol_m=CHAIN_JOINT_TOL_M)
        combined = []
        for n, rms, a, R, t in scored:
            rest = pool[~np.isin(pool, list(a.values()))]
            elbow = R @ model.joint_offsets_m[c] + t
            for n2, rms2, a2, *_ in _around_joint(model, elbow, los[:0], los, cur, points, rest, True, CHAIN_JOINT_TOL_M):
                combined.append((n + n2, max(rms, rms2), a, a2))
        # k's placement first, by the best combination each gives; then the child's under it, if it is
        # as clear (its markers may slide: a finger's on a serving forearm)
        combined.sort(key=lambda x: (-x[0], x[1]))
        firsts = {}
        for x in combined:
            firsts.setdefault(tuple(sorted(x[2].items())), x)
        least = CHAIN_MIN_MARKERS - len(mine_lab)
        mine = _unambiguous(list(firsts.values()), 0, least)
        if mine is not None:
            return mine, _unambiguous([(n, r, a2) for n, r, a, a2 in combined if a == mine], 0, least) or {}
    return None, {}


def _joint_residual(off: np.ndarray, o: np.ndarray, pts: np.ndarray) -> tuple[float, float]:
    """Segment markers at offsets `off` (n, 3) registered onto points `pts` (n, 3): (RMS of the markers'
    misfit, distance between where that puts the segment's joint and `o`)."""
    R, t = rigid_motion(off, pts)
    return float(np.sqrt(np.mean(np.sum((off @ R.T + t - pts) ** 2, 1)))), float(_norm(t - o))


def _rival_fits(model: SubjectModel, pw: np.ndarray, points: np.ndarray, assignment: dict[int, int], k: int,
                segments: np.ndarray) -> bool:
    """Whether the points a search gave segment k fit another segment searched for (`segments`) about as
    well: its markers' layout as well, and its joint not clearly farther. The two hands, hidden together,
    are each other's mirror image; three markers alone cannot tell them apart, and when neither elbow is
    held (the upper arms and trunk hidden too) a stale joint cannot either: the left forearm's search took
    the right hand's three points (tennis serve at L3) and kept them for 140 frames."""
    off, seg = model.marker_offsets_m, model.marker_segment
    mk = np.array(list(assignment))
    pts = points[list(assignment.values())]
    rms, joint = _joint_residual(off[mk], pw[k], pts)
    for k2 in segments:
        idx = np.flatnonzero(seg == k2)
        if k2 == k or len(idx) < len(mk):
            continue
        # every labelling of the points from segment k2's markers at once (a compiled loop)
        limit = max(SEARCH_INLIER_M, 1.5 * rms)
        rms2, joint2 = kernels.segment_fits(off, pw[k2], pts, idx[_arrangements(len(idx), len(mk))], limit)
        if np.any((rms2 < limit) & (joint2 < joint + RIVAL_JOINT_MARGIN_M)):
            return True
    return False


@functools.lru_cache(maxsize=None)
def _arrangements(n: int, k: int) -> np.ndarray:
    """(C, k) every ordered choice of k of n indices (itertools.permutations), as an array."""
    return np.array(list(itertools.permutations(range(n), k)), dtype=np.int64).reshape(-1, k)


def _placed(off: np.ndarray, los: np.ndarray, R: np.ndarray, t: np.ndarray, points: np.ndarray,
            near: np.ndarray, inlier_m: float = SEARCH_INLIER_M) -> dict[int, int]:
    """{marker: point}: markers `los` (offsets `off`) that the segment's motion (R, t) puts within
    `inlier_m` of a point `near`, each on its nearest."""
    d = _norm((off[los] @ R.T + t)[:, None] - points[near][None])
    best = np.argmin(d, axis=1)
    ok = d[np.arange(len(los)), best] < inlier_m
    return {int(los[r]): int(near[best[r]]) for r in np.flatnonzero(ok)}


def _unambiguous(scored: list, margin: int = 0, least: int = 3) -> dict[int, int] | None:
    """The best of scored (n markers placed, RMS, assignment, ...) hypotheses, if it places `least` markers or
    more and no other assignment places as many (less `margin`) about as well."""
    if not scored:
        return None
    scored.sort(key=lambda x: (-x[0], x[1]))
    n, r, assignment = scored[0][:3]
    if n < least or any(n2 >= n - margin and a2 != assignment and r2 < 1.5 * r + 0.003 for n2, r2, a2, *_ in scored[1:]):
        return None
    return assignment


def _triangle_matches(A: np.ndarray, P: np.ndarray, tol_m: tuple) -> list:
    """Every ordered triple of points P (N, 3) at the mutual distances of the triangle A (3, 3), within
    tol_m (per side: ab, ac, bc) [m], as (R, t, residual (3,) [m]): the rigid motion (Kabsch) taking A onto
    those points, and how far each corner then lies from its point. The searches that place a segment or a
    cluster by its layout alone start here."""
    D = _norm(P[:, None] - P[None])
    ab, ac, bc = (np.abs(D - _norm(A[u] - A[v])) < tol for (u, v), tol in zip(((0, 1), (0, 2), (1, 2)), tol_m))
    matches = []
    for a, b in zip(*np.nonzero(ab)):
        for c in np.flatnonzero(ac[a] & bc[b]):
            if c == a or c == b:
                continue
            R, t = rigid_motion(A, P[[a, b, c]])
            matches.append((R, t, _norm(A @ R.T + t - P[[a, b, c]])))
    return matches


def _search_free_segment(model: SubjectModel, pw: np.ndarray, points: np.ndarray, pool: np.ndarray,
                         los: np.ndarray, k: int, observed: np.ndarray) -> dict[int, int] | None:
    """{marker: point} for segment k, none of whose markers `los` is labeled, when its joint cannot anchor
    the search (its parent moved unseen too), or None: its markers' layout is matched as a free rigid
    body. Three of its markers are matched to unclaimed points at the same mutual distances, within reach
    of the grandparent joint (the shoulder for a forearm, held by the trunk); the rigid motion must put
    the segment's joint at its bone's length from there; it then places the other markers. When the
    grandparent moved unseen too, the anchor is the first joint up the chain that an observed segment
    holds, and the joint must lie within the chain's length of it (a foot whose shank and thigh, one
    marker each, hid while the subject walked on hangs from the hip: 85_12 at L3, where the stale knee and
    ankle were 40-65 cm off and the foot stayed unlabeled). Only markers that keep their layout on the
    segment take part.

    What is taken: from the widest triangle, the hypothesis placing most markers, four or more, if no other
    places as many less one about as well (`_unambiguous`: no joint pins it, so a rival one marker short
    counts too). Failing that, where one bone pins the joint, every triangle of the lost markers is tried
    (a serving forearm's wrist pair and finger were in view for 0.5 s while its fourth marker hid with the
    upper arm, and stayed unlabeled: tennis at L3): the best placement, if its triangle fits within
    SEARCH_THREE_RMS_M, merged with every placement agreeing with it (`_consensus`), unless a disagreeing
    one fits about as well with half its support or more. Three markers are a triangle, which fits its
    mirror image (the other hand's) by a turn: only the bone's length tells the two apart, and a chain's
    reach is too loose for that (a foot's three were once matched to two of them and the shank's marker:
    HDM05 at L3, T-pose mode)."""
    parent = PARENTS[k]
    if model.layout_rms_m is None or len(model.layout_rms_m) != model.n_markers or model.layout_offsets_m is None:
        return None  # layouts unmeasured (a calibration saved before they were kept)
    los = los[model.layout_rms_m[los] < SHAPE_LAYOUT_TOL_M]  # a marker that slides (a finger) misplaces it
    if parent < 0 or len(los) < 3:
        return None
    # the calibrated layout, not the offsets refinements on the engine's own labels may have moved (a foot
    # marker refined while labeled on a neighbour's point left the foot unfound, cmu/85_12 at L3)
    off = model.layout_offsets_m
    top, bones = parent, [_norm(model.joint_offsets_m[k])]  # up the unobserved chain to a held joint
    while PARENTS[top] >= 0 and not observed[top] and not observed[PARENTS[top]]:
        bones.append(_norm(model.joint_offsets_m[top]))
        top = PARENTS[top]
    one_bone = len(bones) == 1
    if not one_bone and len(los) < 4:
        return None
    anchor, reach = pw[top], sum(bones)
    joint = model.layout_joints_m[k]  # (where the layout is placed, the model's joint: see layout_joints_m)
    # (the joint lies within its bone's tolerance of the reach, and each marker within its offset of the joint)
    near = pool[_norm(points[pool] - anchor) < reach + SEARCH_BONE_TOL_M + _norm(off[los]).max()]
    if len(near) < 3:
        return None

    def area(c):
        return _norm(np.cross(off[c[1]] - off[c[0]], off[c[2]] - off[c[0]]))

    triangles = sorted(itertools.combinations(los, 3), key=area, reverse=True)

    def placements(tris, tol: float) -> list:
        """(n placed, RMS of the triangle's fit, {marker: point}), most placed first, from the triangles
        `tris` matched within `tol` times the search's tolerances (side lengths, corner residuals, the joint
        off its bone's length)."""
        scored, seen = [], set()
        for tri in tris:
            for R, t, res in _triangle_matches(off[list(tri)], points[near], (tol * SEARCH_PAIR_TOL_M,) * 3):
                d = _norm(R @ joint + t - anchor)  # one bone: at its length; a chain: within its reach
                if res.max() > tol * 2 * SEARCH_INLIER_M or (abs(d - reach) if one_bone else d - reach) > tol * SEARCH_BONE_TOL_M:
                    continue
                assignment = _placed(off, los, R, t, points, near)
                key = tuple(sorted(assignment.items()))
                if len(set(assignment.values())) < len(assignment) or key in seen:
                    continue  # (another triangle of the same placement)
                seen.add(key)
                if len(assignment) >= 3:  # (its own corners at least: one may miss the inlier gate)
                    scored.append((len(assignment), float(np.sqrt(np.mean(res**2))), assignment))
        return sorted(scored, key=lambda x: (-x[0], x[1]))

    scored = placements(triangles[:1], 1.0) if len(los) >= 4 else []  # the widest, and a fourth marker
    if scored and scored[0][0] >= 4:
        return _unambiguous(scored, 1, 4)
    if not one_bone:
        return None
    scored = placements(triangles, 1.0)
    if not scored or scored[0][1] > SEARCH_THREE_RMS_M:
        return None
    # Each triangle placed alone: the placement is the best one's consensus, every placement agreeing with
    # it merged in (a forearm of five markers twisting under pronation fits no rigid layout within the
    # inlier gate, but four of its triangles each placed three of them, consistently: two players at L3,
    # the left forearm unlabeled 100 frames in view). A rival is a placement disagreeing with it about as
    # good, within RIVAL_TOL_FACTOR times the tolerances (a foot's ankle, fifth metatarsal and toe are
    # nearly isosceles: with ankle and toe swapped they fitted the search's tolerances, the true labels, 13
    # mm off in two sides, did not, and the swap was taken: cmu/135_02 at L3, the foot wrong for 500
    # frames); it makes the placement ambiguous unless its own consensus has less than half the support.
    loose = placements(triangles, RIVAL_TOL_FACTOR)
    assignment, support = _consensus(scored[0][2], loose)
    for _, r2, a2 in loose:
        if r2 < 1.5 * scored[0][1] + 0.003 and not _agrees(assignment, a2) and 2 * _consensus(a2, loose)[1] >= support:
            return None
    return assignment


def _agrees(a: dict[int, int], b: dict[int, int]) -> bool:
    """Whether two {marker: point} placements agree: no marker on two points, no point for two markers."""
    taken = {p: i for i, p in a.items()}
    return all(a.get(i, p) == p and taken.get(p, i) == i for i, p in b.items())


def _consensus(seed: dict[int, int], placements: list) -> tuple[dict[int, int], int]:
    """`seed` merged with every placement (n, RMS, {marker: point}) agreeing with it so far, best first,
    and how many placements it merged (the seed's own counted)."""
    merged, support = dict(seed), 0
    for _, _, a in placements:
        if _agrees(merged, a):
            merged.update(a)
            support += 1
    return merged, max(support, 1)  # (the seed is among them when it came from the same search)


@functools.lru_cache(maxsize=None)
def _triples(n: int) -> np.ndarray:
    """(C, 3) every choice of 3 of n indices, in itertools.combinations order."""
    return np.array(list(itertools.combinations(range(n), 3)), dtype=np.int64).reshape(-1, 3)


def _search_rigid_groups(st: TrackState, points: np.ndarray, pool: np.ndarray, labeled: np.ndarray,
                         cur: np.ndarray, lost: np.ndarray) -> dict[int, int]:
    """Which points markers `lost` are now, {marker: point}, for a subject with no skeleton (a seed taken lying
    down: numediart/03_rolling rolls on the floor, where a limb's cluster hides whole, and nothing placed it
    again once it did). Without segments, the groups are what the partner statistics say moves rigidly now:
    lost markers whose distances to one another all varied by under GROUP_SD_M. A group's layout is where its
    markers were when its first marker was last labeled (`snap_m`); its widest triangle is matched to
    unclaimed points at the same mutual distances, within the reach the distance statistics allow from every
    labeled marker (the body holds a thigh's cluster within a metre of the head, whatever the pose), and the
    rigid motion places the group's other markers. A group's best hypothesis, GROUP_MIN_PLACED markers placed
    or more (three, the triangle alone, took wrong points: 03_rolling's precision at L0 fell from 98.6 to 90 %
    in a trial), is taken if no other assignment of it does about as well (`_unambiguous`), and no other
    group's fits the same points about as well (the left hand's cluster fits the right hand's points when they
    are mirror images: the two hands stay unfound while both are lost and one is in view)."""
    sd = np.sqrt(st.dist_var_m2)
    known = st.dist_n >= PARTNER_MIN_SAMPLES
    rigid = known & (np.maximum(sd, np.sqrt(st.dist_slow_var_m2)) < GROUP_SD_M)  # now and over the long memory
    seeds = np.flatnonzero(lost & ((rigid & lost).sum(1) >= GROUP_MIN_PLACED - 1))
    if len(seeds) == 0 or len(pool) < 3:
        return {}  # (most frames: no group hidden whole, nothing to compute)
    lab = np.flatnonzero(labeled)
    d_lab = _norm(points[pool][:, None] - cur[lab][None])  # (pool, labeled) for the reach
    grouped = np.zeros(len(lost), bool)
    best = []  # per group: (n placed, RMS, {marker: point})
    for i in seeds:
        if grouped[i]:
            continue
        layout = st.snap_m[i]
        # the lost markers rigid to every member, most rigid to i first (a greedy clique)
        order = np.argsort(sd[i])
        order = order[lost[order] & ~grouped[order] & rigid[order, i] & np.isfinite(layout[order, 0]) & (order != i)]
        group = [i]
        for j in order:
            if rigid[j, group].all():
                group.append(j)
        group = np.array(group)
        if len(group) < GROUP_MIN_PLACED:
            continue
        grouped[group] = True
        off = layout[group]
        # reach: each group marker within its mean distance + 4 sigma (+ GROUP_REACH_M) of every labeled
        # marker whose distance to it is known
        bound = np.where(known[np.ix_(group, lab)], st.dist_mean_m[np.ix_(group, lab)] + 4.0 * sd[np.ix_(group, lab)]
                         + GROUP_REACH_M, np.inf)
        near = pool[(d_lab[:, None, :] <= bound[None]).all(axis=(1, 2))]
        if len(near) < 3:
            continue
        triples = _triples(len(group))  # the widest triangle
        tri = triples[np.argmax(_norm(np.cross(off[triples[:, 1]] - off[triples[:, 0]],
                                               off[triples[:, 2]] - off[triples[:, 0]])))]
        A, tri = off[list(tri)], group[list(tri)]
        tol = tuple(GROUP_PAIR_TOL_M + 3.0 * sd[tri[u], tri[v]] for u, v in ((0, 1), (0, 2), (1, 2)))
        scored = []
        for R, t, res in _triangle_matches(A, points[near], tol):
            if res.max() > GROUP_INLIER_M:
                continue
            placed = _placed(off, np.arange(len(group)), R, t, points, near, GROUP_INLIER_M)
            if len(set(placed.values())) < len(placed):
                continue
            scored.append((len(placed), float(np.sqrt(np.mean(res**2))), {int(group[r]): p for r, p in placed.items()}))
        assignment = _unambiguous(scored, 0, GROUP_MIN_PLACED)
        if assignment:
            n, r = scored[0][:2]
            best.append((n, r, assignment))
    found: dict[int, int] = {}
    for n, r, assignment in best:
        pts = set(assignment.values())
        if not any(n2 >= n - 1 and r2 < 1.5 * r + 0.003 and pts & set(a2.values()) for n2, r2, a2 in best
                   if a2 is not assignment):
            found.update(assignment)
    return found


def _kabsch_rms(A: np.ndarray, B: np.ndarray, w: np.ndarray) -> np.ndarray:
    """RMS misfit (C,) of the best rigid motion taking A onto B, both (C, N, 3), over the points where
    w (C, N) is True. The optimal trace is s1 + s2 + sign(det H) s3 over the singular values of the
    cross-covariance H (Kabsch), so no rotation is formed, and they are the square roots of H^T H's
    eigenvalues, in closed form (the trigonometric solution of the characteristic cubic)."""
    # (a compiled loop, `kernels`: one call instead of ~50 numpy calls on small batches; A and B may be
    # broadcast views, the kernel takes writable contiguous arrays of one type: one compilation)
    return kernels.kabsch_rms(np.require(A, np.float64, "CW"), np.require(B, np.float64, "CW"), np.require(w, bool, "CW"))


def _layout_fits(model: SubjectModel, cur: np.ndarray, sel: np.ndarray, ks: np.ndarray):
    """Segments ks's markers `sel` (M,) (all on a segment) registered onto their layout in one batch:
    (members, sorted by segment; the index in ks of each one's segment; how many each segment has; each
    segment's RMS misfit [m]; each segment's markers' own layout residual, RMS [m])."""
    seg = model.marker_segment
    wanted = np.zeros(N_SEGMENTS, bool)
    wanted[ks] = True
    members = np.flatnonzero(sel & wanted[seg])
    members = members[np.argsort(seg[members], kind="stable")]
    row = np.searchsorted(ks, seg[members])
    return (members, row) + _registered_rows(model, members, cur[members], row, len(ks))


def _registered_rows(model: SubjectModel, members: np.ndarray, at_m: np.ndarray, row: np.ndarray, n_rows: int):
    """Markers `members` seen at `at_m`, grouped in rows (`row`, ascending), each row registered onto their
    layout: (how many markers each row has, its RMS misfit [m], its markers' own layout residual, RMS
    [m]). The rows are padded rows of one array, built with array operations: a list of per-row lookups
    cost more than the registration itself."""
    n_lab = np.bincount(row, minlength=n_rows)
    col = np.arange(len(members)) - np.concatenate([[0], np.cumsum(n_lab)[:-1]])[row]
    width = int(n_lab.max())
    A = np.zeros((n_rows, width, 3))
    B = np.zeros((n_rows, width, 3))
    w = np.zeros((n_rows, width), bool)
    A[row, col], B[row, col], w[row, col] = model.layout_offsets_m[members], at_m, True
    typical = np.sqrt(np.bincount(row, model.layout_rms_m[members] ** 2, minlength=n_rows) / n_lab)
    return n_lab, _kabsch_rms(A, B, w), typical


def _fit_tolerance(n_lab: np.ndarray, typical: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(whether a relabelling of each segment could be taken on clear evidence, the RMS [m] within which
    its labels fit its layout). A segment fits when its labels sit about as well as they did in
    calibration: a few times its markers' own layout residual (1-2 mm on a foot), and never worse than
    SHAPE_MIN_RMS_M. A fixed 12 mm let a toe label on the fifth metatarsal's point pass (10 mm, 85_12 at
    L2) for 1.6 s. (Only where a relabelling could then be taken on clear evidence: checking the others
    costs time.)"""
    can_clear = (n_lab >= SHAPE_CLEAR_MIN_LABELS) & (typical <= SHAPE_CLEAR_HANDOVER_LAYOUT_M)
    tol = np.where(can_clear, np.minimum(SHAPE_MIN_RMS_M, np.maximum(SHAPE_FIT_FLOOR_M, SHAPE_FIT_FACTOR * typical)), SHAPE_MIN_RMS_M)
    return can_clear, tol


def _layout_slots(model: SubjectModel, st: TrackState) -> np.ndarray | None:
    """(M,) the markers the layout checks judge: ever seen, and their calibrated layout held within
    SHAPE_LAYOUT_TOL_M (NaN compares False); None if the model has no measured layout."""
    if model.layout_rms_m is None or len(model.layout_rms_m) != model.n_markers or model.layout_offsets_m is None:
        return None
    return st.ever_seen & (model.marker_segment >= 0) & (model.layout_rms_m < SHAPE_LAYOUT_TOL_M)


def _trusted_layouts(st: TrackState) -> np.ndarray:
    """(N_SEGMENTS,) segments whose labels fitted their layout on enough checks for it to be trusted."""
    return (st.shape_fit >= SHAPE_TRUSTED_SHARE) & (st.shape_checks > SHAPE_MIN_CHECKS)


def _layout_tolerance(model: SubjectModel, markers: np.ndarray) -> float:
    """[m] RMS within which these markers fit their layout when labeled right (`_tolerance_of`)."""
    return float(_tolerance_of(np.sqrt(np.mean(model.layout_rms_m[markers] ** 2))))


def _tolerance_of(typical):
    """COMPLETE_FIT_FACTOR times a calibration residual `typical` [m] (RMS), at least SHAPE_CLEAR_FIT_M."""
    return np.maximum(SHAPE_CLEAR_FIT_M, COMPLETE_FIT_FACTOR * typical)


def _partners_object(st: TrackState, points: np.ndarray, cur: np.ndarray, labeled: np.ndarray,
                     proposed: np.ndarray, moved: np.ndarray) -> bool:
    """Whether the long-run partner distances object to moving the `moved` markers' labels to the points
    `proposed` gives them: they have taken a long-standing permutation in (what the layout checks undo)
    but refuse a fresh one (a layout near-symmetric under it, a skin-moved segment)."""
    z_now = distance_misfit(st, cur, labeled, moved)[moved]
    z_new = distance_misfit(st, _gather(points, proposed), proposed >= 0, moved)[moved]
    z_now, z_new = z_now[np.isfinite(z_now)], z_new[np.isfinite(z_new)]
    return bool(len(z_new) and np.median(z_new) > max(Z_SUSPECT, 2.0 * (np.median(z_now) if len(z_now) else 0.0)))


def _labelings_fit(model: SubjectModel, slot: np.ndarray, maps: np.ndarray, joint_m: np.ndarray,
                   pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each of P point triples `pts` (P, 3, 3) under each of C labelings `maps` (C, 3) of a segment's
    `slot` markers: (C, P) RMS of the points registered onto the calibrated layout, and of the points and
    the segment's joint `joint_m` registered onto the marker offsets and the segment's origin."""
    C, P = len(maps), len(pts)
    B = np.empty((P, 4, 3))
    B[:, 0], B[:, 1:] = joint_m, pts
    B = np.broadcast_to(B[None], (C, P, 4, 3)).reshape(-1, 4, 3)  # labelling-major
    rms3 = _kabsch_rms(np.repeat(model.layout_offsets_m[slot[maps]], P, axis=0), B[:, 1:], np.ones((C * P, 3), bool))
    A = np.concatenate([np.zeros((C * P, 1, 3)), np.repeat(model.marker_offsets_m[slot[maps]], P, axis=0)], axis=1)
    rms4 = _kabsch_rms(A, B, np.ones((C * P, 4), bool))
    return rms3.reshape(C, P), rms4.reshape(C, P)


def _segment_counts(model: SubjectModel, st: TrackState, point_index: np.ndarray):
    """The layout checks' view of the labels: (slots, labeled, n_lab, n_spare), with each segment's
    labeled and unlabeled layout markers counted (N_SEGMENTS,), or None if no layout was measured."""
    slots = _layout_slots(model, st)
    if slots is None:
        return None
    labeled = point_index >= 0
    seg = model.marker_segment
    n_lab = np.bincount(seg[labeled & slots], minlength=N_SEGMENTS)
    n_spare = np.bincount(seg[~labeled & slots], minlength=N_SEGMENTS)
    return slots, labeled, n_lab, n_spare


def _complete_by_free_point(model: SubjectModel, st: TrackState, points: np.ndarray, cand: np.ndarray,
                            point_index: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Put back two labels of a segment permuted while its other markers hide, using a free point and the
    segment's joint. In place; returns the markers whose point changed.

    Two labels alone match one distance, which a swap keeps: a foot's toe and fifth metatarsal labels
    swapped as the foot came back (the heel hidden) stayed swapped for 13 s, and the heel's point, in
    view, stayed unlabeled, its prediction carried by the swapped pair (HDM05 at L3). For each segment
    with two labeled markers and unlabeled ones, the two points, each free point within the segment's
    reach and the joint where the latest fit puts it are registered onto the segment's markers under
    every way of labeling the points from them. A labeling counts if its three points fit the calibrated
    layout within COMPLETE_FIT_FACTOR times its markers' calibration residual (at least
    COMPLETE_FIT_FLOOR_M: skin and joint motion the seed did not show); the one whose joint then
    fits best is taken if it permutes the two labels, fits within COMPLETE_JOINT_RMS_M, and another
    labeling of the two points fits the layout too but puts the joint clearly farther off: the ambiguity
    the joint resolves (heel, toe and fifth metatarsal make a near-isosceles triangle; its mirror image
    fits it as well). Where no other labeling fits the layout, the free point is as likely a stray one
    completing a wrong triangle (a torso's markers at L2): left alone, unless the two labels themselves
    misfit the layout's distance between them by COMPLETE_PAIR_MISFIT_M (a tennis wrist marker
    re-acquired on its neighbour's point after the serve, 29 mm off, stayed there 40 frames with its own
    point free beside it). The pair is wrong then, rivalled or not: the joint still tells rivals apart,
    but otherwise only guards against a far-fetched triangle (COMPLETE_WRONG_PAIR_JOINT_M). A skeleton
    fitting at 20-30 mm put a tennis player's ankle joint 5-9 cm from a heel label on the toe's point,
    which stayed there 2.3 s; once the floor let a wrong labeling, its joint 12 cm off, fit a forearm's
    layout too, wrist labels on the finger's and forearm's points (joint 44 mm off) stayed there 5 s. But
    a pair can misfit its layout by the skin's doing (a forearm under pronation, 10-15 mm): where the pair
    as labeled, with any free point, fits the joint within COMPLETE_JOINT_RMS_M and by SHAPE_CLEAR_MIN_M
    better than the relabelling, it is kept (a forearm's right wrist labels so swapped onto each other's
    points stayed swapped 3 s, 135_02 at L3; dev suite, 18 realizations: 3 L3 runs up, L3 98.025 ->
    98.035 %, none down, L2 and the off-suite files unchanged). As in `_relabel_by_shape`, the same
    relabelling must win SHAPE_CONFIRM checks running on a trusted layout, and the long-run partner
    distances must not object; the free point's label is on probation."""
    counts = _segment_counts(model, st, point_index)
    if counts is None:
        return np.zeros(len(point_index), bool)
    slots, labeled, n_lab, n_spare = counts
    seg, layout = model.marker_segment, model.layout_offsets_m
    trusted = _trusted_layouts(st)
    pool = np.flatnonzero(cand)
    before = point_index.copy()
    small = n_lab + n_spare <= SHAPE_ALL_MAPS + 1  # every labeling of three of its markers is tried
    checked = np.flatnonzero((n_lab == 2) & (n_spare > 0) & small & trusted)
    if len(checked):
        pw = _joints_m(model, st)
    for k in checked:
        lab = np.flatnonzero(labeled & slots & (seg == k))
        slot = np.concatenate([lab, np.flatnonzero(~labeled & slots & (seg == k))])
        reach = _norm(layout[slot] - layout[slot].mean(0)).max() * 2.0 + SEARCH_INLIER_M
        near = pool[_norm(points[pool] - cur[lab].mean(0)) < reach]
        if len(near) == 0:
            st.complete_votes.pop(int(k), None)
            continue
        maps = _relabellings(3, len(slot))  # (C, 3): slots labeling the two points, then the free one
        # every (labelling, free point) pair: the two points and the free one
        triples = np.concatenate([np.broadcast_to(cur[lab], (len(near), 2, 3)), points[near][:, None]], axis=1)
        rms3, rms4 = _labelings_fit(model, slot, maps, pw[k], triples)
        # (a floor: a foot's layout, measured to 0.9 mm in the seed, fitted its true labels to 3.7 mm once the
        # ankle flexed, and a toe label stayed on the fifth metatarsal's point 1.7 s; 85_12 at L3)
        tight = max(_layout_tolerance(model, slot), COMPLETE_FIT_FLOOR_M)
        score = np.where(rms3 <= tight, rms4, np.inf)
        c, p = np.unravel_index(int(np.argmin(score)), score.shape)
        other = (maps[:, 0] != maps[c, 0]) | (maps[:, 1] != maps[c, 1])  # another labeling of the two points
        rival = score[other].min() if other.any() else np.inf
        pair_misfit = abs(_norm(cur[lab[0]] - cur[lab[1]]) - _norm(layout[lab[0]] - layout[lab[1]]))
        wrong_pair = pair_misfit >= COMPLETE_PAIR_MISFIT_M
        if wrong_pair:
            # the pair as labeled, its misfit and all, with whichever free point: where the joint fits it
            # as a right labeling should and clearly better than the relabelling, the misfit is the skin's
            kept = rms4[(maps[:, 0] == 0) & (maps[:, 1] == 1)].min()
            if kept <= COMPLETE_JOINT_RMS_M and kept + SHAPE_CLEAR_MIN_M <= score[c, p]:
                st.complete_votes.pop(int(k), None)
                continue
        if not ((np.isfinite(rival) or wrong_pair) and (maps[c, 0], maps[c, 1]) != (0, 1) and rival >= 2.0 * score[c, p] + SHAPE_CLEAR_MIN_M
                and score[c, p] <= (COMPLETE_WRONG_PAIR_JOINT_M if wrong_pair else COMPLETE_JOINT_RMS_M)):
            st.complete_votes.pop(int(k), None)
            continue
        new = (int(slot[maps[c, 0]]), int(slot[maps[c, 1]]), int(slot[maps[c, 2]]), int(near[p]))
        votes = st.complete_votes.get(int(k), ((), 0))  # (the points are renumbered every frame: markers only)
        # (the vote is on the pair's labels: with two of its markers hidden, the free point completing the
        # triangle may be either, frame by frame; a tennis wrist and finger, 2026-11-25)
        votes = (new[:2], votes[1] + 1 if votes[0] == new[:2] else 1)
        st.complete_votes[int(k)] = votes
        if votes[1] < SHAPE_CONFIRM:
            continue
        del st.complete_votes[int(k)]
        proposed = point_index.copy()
        proposed[lab] = -1
        proposed[[new[0], new[1]]] = point_index[lab]
        proposed[new[2]] = new[3]
        if _partners_object(st, points, cur, labeled, proposed, np.flatnonzero(proposed != point_index)):
            continue
        point_index[:] = proposed
        st.provisional[new[2]] = PROBATION_FRAMES
        pool = pool[pool != new[3]]
        cur[:] = _gather(points, point_index)
        labeled = point_index >= 0
    return point_index != before


def _complete_lone_label(model: SubjectModel, st: TrackState, points: np.ndarray, cand: np.ndarray,
                         point_index: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Put back a segment's one label sitting on another of its markers' points, and label its hidden
    markers, from two free points and the segment's joint. In place; returns the markers whose point
    changed.

    A tennis player's whole foot hid as the serve turned it: its markers came back where neither the
    shank's markers nor the fit put them, the Hungarian gave the ankle label the toe's point, and with the
    heel's and the ankle's own points left free (their predictions followed the wrong label) one label
    alone matched nothing to check: it stayed there 6.5 s (L3). As in `_complete_by_free_point`, the
    labeled point with every two free points within the segment's reach, and the joint where the latest fit
    puts it, are registered onto the segment's markers under every way of labeling the three points; the
    labeling whose three points fit the layout (COMPLETE_FIT_FACTOR) and whose joint then fits best is
    taken if it fits within COMPLETE_JOINT_RMS_M and every labeling that gives the labeled point another
    label fits clearly worse (twice, plus SHAPE_CLEAR_MIN_M). The same labeling must win SHAPE_CONFIRM checks
    running on a trusted layout, and the long-run partner distances must not object; the two free points'
    labels are on probation. (Dev suite, 18 realizations: L3 98.018 -> 98.059 %, 9 runs up, none down; L2
    99.238 -> 99.241 %.)"""
    changed = np.zeros(len(point_index), bool)
    counts = _segment_counts(model, st, point_index)
    if counts is None:
        return changed
    slots, labeled, n_lab, n_spare = counts
    seg, layout = model.marker_segment, model.layout_offsets_m
    small = n_lab + n_spare <= SHAPE_ALL_MAPS + 1  # every labeling of three of its markers is tried
    checked = np.flatnonzero((n_lab == 1) & (n_spare >= 2) & small & _trusted_layouts(st))
    if not len(checked):
        return changed
    pool = cand.copy()
    pool[point_index[labeled]] = False  # (points labeled since `cand` was made: `_complete_by_free_point`)
    pool = np.flatnonzero(pool)
    pw = _joints_m(model, st)
    for k in checked:
        key = -1 - int(k)  # (its votes beside `_complete_by_free_point`'s, which are keyed by segment)
        lab = np.flatnonzero(labeled & slots & (seg == k))
        slot = np.concatenate([lab, np.flatnonzero(~labeled & slots & (seg == k))])
        reach = _norm(layout[slot] - layout[slot].mean(0)).max() * 2.0 + SEARCH_INLIER_M
        near = pool[_norm(points[pool] - cur[lab[0]]) < reach]
        if len(near) < 2:
            st.complete_votes.pop(key, None)
            continue
        pairs = np.array(list(itertools.combinations(near, 2)))  # (P, 2): every labeling below orders them
        maps = _relabellings(3, len(slot))  # (C, 3): slots labeling the labeled point, then the two free ones
        triples = np.concatenate([np.broadcast_to(cur[lab], (len(pairs), 1, 3)), points[pairs]], axis=1)
        rms3, rms4 = _labelings_fit(model, slot, maps, pw[k], triples)
        tight = max(_layout_tolerance(model, slot), COMPLETE_FIT_FLOOR_M)
        score = np.where(rms3 <= tight, rms4, np.inf)
        c, p = np.unravel_index(int(np.argmin(score)), score.shape)
        other = maps[:, 0] != maps[c, 0]  # the labeled point under another label
        rival = score[other].min() if other.any() else np.inf
        if not (score[c, p] <= COMPLETE_JOINT_RMS_M and rival >= 2.0 * score[c, p] + SHAPE_CLEAR_MIN_M):
            st.complete_votes.pop(key, None)
            continue
        new = tuple(int(i) for i in slot[maps[c]])  # (the points are renumbered every frame: markers only)
        # (the vote is on the labeled point's label: which of the two free points is which follows their
        # numbering, frame by frame; a vote on all three labels missed a tennis wrist's swap for 26 frames)
        votes = st.complete_votes.get(key, ((), 0))
        votes = (new[:1], votes[1] + 1 if votes[0] == new[:1] else 1)
        st.complete_votes[key] = votes
        if votes[1] < SHAPE_CONFIRM:
            continue
        del st.complete_votes[key]
        proposed = point_index.copy()
        proposed[lab[0]] = -1
        proposed[list(new)] = [point_index[lab[0]], *pairs[p]]
        moved = np.flatnonzero(proposed != point_index)
        if _partners_object(st, points, cur, labeled, proposed, moved):
            continue
        point_index[moved] = proposed[moved]
        changed[moved] = True
        st.provisional[list(new[1:])] = PROBATION_FRAMES
        pool = pool[~np.isin(pool, pairs[p])]
        cur[:] = _gather(points, point_index)
        labeled = point_index >= 0
    return changed


def _reseat_outliers(model: SubjectModel, st: TrackState, points: np.ndarray, cand: np.ndarray,
                     point_index: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Move a label its segment's layout says is off to the point where the layout puts it. In place;
    returns the markers whose point changed.

    A wrist marker tracked onto the waist marker's point as the hand rested on the hip (and the waist's
    label onto the wrist's) stays there: the two points lie 4-5 cm apart, about as far from every partner,
    so no distance tells, and no permutation within either segment undoes a swap between segments (135_02
    at L2, 0.6 s). The forearm's other labels still fit its layout: registered without the outlier, they
    put it on its own point. For each segment with a trusted layout and RESEAT_MIN_LABELS labels or more
    that misfits it, the one label whose leaving out makes the rest fit (RESEAT_SHARE; leaving out any
    other fits at least twice as badly) is moved to the point nearest where the rest put it, within
    RESEAT_RADIUS_M: a free point, or another segment's label's point, whose label then takes the
    outlier's point if its long-run partner distances do not object. The same move must win SHAPE_CONFIRM
    checks running. (Dev suite, 8 files x L2/L3 x 6 corruption seeds: L2 99.01 -> 99.10 %, L3 97.18 ->
    97.27 %.)"""
    changed = np.zeros(len(point_index), bool)
    slots = _layout_slots(model, st)
    if slots is None:
        return changed
    labeled = point_index >= 0
    seg, layout = model.marker_segment, model.layout_offsets_m
    n_lab = np.bincount(seg[labeled & slots], minlength=N_SEGMENTS)
    trusted = _trusted_layouts(st)
    proposed = set()
    ks = np.flatnonzero((n_lab >= RESEAT_MIN_LABELS) & trusted)
    if not len(ks):
        return changed
    # first every segment's labels at once: most fit, and only those that misfit are looked at one by one
    # (a loop over all of them cost ~0.3 ms on every check)
    *_, rms_all, typical = _layout_fits(model, cur, labeled & slots, ks)
    misfit = rms_all > RESEAT_MISFIT_FACTOR * _tolerance_of(typical)
    for r, k in enumerate(ks):
        if not (misfit[r] or changed.any()):  # (a move below changes the labels the batch judged)
            continue
        lab = np.flatnonzero(labeled & slots & (seg == k))
        n = len(lab)
        tight = _layout_tolerance(model, lab)
        # all labels, then each left out (one batch)
        w = np.ones((n + 1, n), bool)
        w[np.arange(1, n + 1), np.arange(n)] = False
        rms = _kabsch_rms(np.broadcast_to(layout[lab], (n + 1, n, 3)), np.broadcast_to(cur[lab], (n + 1, n, 3)), w)
        if rms[0] <= RESEAT_MISFIT_FACTOR * tight:
            continue
        order = np.argsort(rms[1:])
        j = int(order[0])
        if not (rms[1 + j] <= max(tight, RESEAT_SHARE * rms[0]) and rms[1 + order[1]] >= 2.0 * rms[1 + j]):
            continue
        i = int(lab[j])
        rest = np.delete(lab, j)
        R, t = rigid_motion(layout[rest], cur[rest])
        x = R @ layout[i] + t
        d = _norm(points - x)
        p = int(np.argmin(d))
        if d[p] > RESEAT_RADIUS_M or p == point_index[i]:
            st.reseat_votes.pop(i, None)
            continue
        owner = np.flatnonzero(point_index == p)
        q = int(owner[0]) if len(owner) else -1
        if q < 0 and not cand[p]:
            continue  # another subject's point
        if q >= 0 and seg[q] == k:
            continue  # a permutation within the segment: `_relabel_by_shape`'s
        votes = st.reseat_votes.get(i, (None, 0))
        votes = (q, votes[1] + 1 if votes[0] == q else 1)
        st.reseat_votes[i] = votes
        proposed.add(i)
        if votes[1] < SHAPE_CONFIRM:
            continue
        del st.reseat_votes[i]
        new = point_index.copy()
        new[i] = p
        if q >= 0:
            new[q] = point_index[i]
            z_now = distance_misfit(st, cur, labeled, np.array([q]))[q]
            z_new = distance_misfit(st, _gather(points, new), new >= 0, np.array([q]))[q]
            if np.isfinite(z_new) and z_new > max(Z_SUSPECT, 2.0 * (z_now if np.isfinite(z_now) else 0.0)):
                continue
        moved = np.flatnonzero(new != point_index)
        point_index[:] = new
        changed[moved] = True
        cur[:] = _gather(points, point_index)
        labeled = point_index >= 0
    for i in [i for i in st.reseat_votes if i not in proposed]:
        del st.reseat_votes[i]
    return changed


def _mirror_by_joint(model: SubjectModel, st: TrackState, k: int, lab: np.ndarray, slot: np.ndarray, maps: np.ndarray,
                     cur: np.ndarray, symmetric: np.ndarray) -> int | None:
    """The relabelling (an index into maps) of segment k's labels `lab` that its joint tells from the
    identity though the layout alone cannot, or None. Three markers match their mirror image by a turn (a
    foot whose heel is as far from the toe as from the fifth metatarsal: toe and metatarsal labels
    swapped fit the layout as well, HDM05 at L3, for 3 s); the joint, where the parent holds it, is a
    fourth point off their plane. Taken when, with the joint, the relabelling fits under JOINT_GAIN times
    the identity, the identity misfits by JOINT_MIN_MISFIT_M or more, and no other fits about as well."""
    cands = np.flatnonzero(symmetric[1:]) + 1
    if len(cands) == 0 or len(lab) < 3 or st.skel_pred_m is None:
        return None
    rows = np.concatenate([[0], cands])
    fit = _joint_fits(model, st, k, lab, slot, maps, rows, cur)
    order = np.argsort(fit[1:])
    best = fit[1 + order[0]]
    if fit[0] < JOINT_MIN_MISFIT_M or best > JOINT_GAIN * fit[0]:
        return None
    if len(order) > 1 and fit[1 + order[1]] < 1.5 * best:
        return None
    return int(rows[1 + order[0]])


def _overwhelming_handovers(st: TrackState, lab: np.ndarray, slot: np.ndarray, maps: np.ndarray, rms: np.ndarray,
                            blocked: np.ndarray, tol: float, where: np.ndarray) -> np.ndarray:
    """(C,) the relabellings of a segment misfitting its layout by SHAPE_SETTLED_HANDOVER_MISFIT_M that hand
    a label tracked all along to an unlabeled marker and fit within `tol`, no label jumping farther than
    SHAPE_MAX_HANDOVER_M from where its marker was: `relabel_candidates` blocked them for the tracked label
    alone; the evidence lifts that block (see SHAPE_SETTLED_HANDOVER_MISFIT_M). Not for a settled label
    (confirmed by the whole layout and tracked since), which no relabelling moves: lifted, its block would
    only make the check propose what it will not take, in place of what it would. Nor where a relabelling
    not blocked fits about as well (twice its RMS + 1 mm, as the check counts rivals): the handover would
    only tie with it, and the tie leave the labels be (a head's near-square layout: the tracked label's
    handover and the other two labels mirrored both fitted, 85_12 at L3, and the head stayed wrong 3 s
    longer than with the mirror taken alone)."""
    handed = maps >= len(lab)
    out = (rms <= tol) & (handed & (st.provisional[lab] <= 0)[None]).any(1) & ~(handed & st.settled[lab][None]).any(1)
    for c in np.flatnonzero(out):
        out[c] = _norm(where[lab] - where[slot[maps[c]]]).max() <= SHAPE_MAX_HANDOVER_M
    if out.any():
        others = ~blocked
        others[0] = False  # (the identity)
        if (rms[others] < 2.0 * rms[out].min() + 0.001).any():
            out[:] = False
    return out


def _joint_fits(model: SubjectModel, st: TrackState, k: int, lab: np.ndarray, slot: np.ndarray, maps: np.ndarray,
                rows: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """(len(rows),) [m] RMS of segment k's labeled points `lab` and its joint, where the latest fit puts
    it, registered onto the layout under each relabelling maps[rows]; all infinite with no fit to ask."""
    if st.skel_pred_m is None:
        return np.full(len(rows), np.inf)
    joint = _joints_m(model, st)[k]
    A = np.concatenate([model.layout_offsets_m[slot[maps[rows]]],
                        np.broadcast_to(model.layout_joints_m[k], (len(rows), 1, 3))], axis=1)
    B = np.broadcast_to(np.vstack([cur[lab], joint[None]]), A.shape)
    return _kabsch_rms(A, B, np.ones(A.shape[:2], bool))


@functools.lru_cache(maxsize=None)
def _relabellings(n: int, s: int | None = None) -> np.ndarray:
    """(C, n) ways to give n labeled points (now on slots 0..n-1 of a segment's s >= n marker slots; the
    slots beyond n are its unlabeled markers) labels from those slots, one each, the identity first: every
    assignment for small segments, else every swap of two labels and every label handed to an unlabeled
    marker (a torso of 7: 21 swaps, not 5040 permutations)."""
    s = n if s is None else s
    if n <= SHAPE_ALL_MAPS and s <= SHAPE_ALL_MAPS + 1:
        return np.array(list(itertools.permutations(range(s), n)), dtype=int)
    maps = [list(range(n))]
    for i, j in itertools.combinations(range(n), 2):
        p = list(range(n))
        p[i], p[j] = j, i
        maps.append(p)
    for i in range(n):
        for u in range(n, s):
            p = list(range(n))
            p[i] = u
            maps.append(p)
    return np.array(maps, dtype=int)


def _count_layout_fits(st: TrackState, ks: np.ndarray, fits: np.ndarray) -> np.ndarray:
    """Fold one check of segments `ks` (whether their labels fit their layouts) into the running share of
    checks that fit; returns the share before it."""
    share = st.shape_fit[ks]
    st.shape_checks[ks] += 1
    alpha = np.maximum(1.0 / st.shape_checks[ks], SHAPE_FIT_ALPHA)  # a plain mean first, then a running one
    st.shape_fit[ks] = share + alpha * (fits - share)
    return share


def learn_layout_trust(model: SubjectModel, st: TrackState, history_m: np.ndarray) -> None:
    """Count how often each segment's labels fit its new layout over the labeled frames (F, M, 3) it was
    calibrated from (every SHAPE_EVERY_FRAMES-th), as the checks of `_relabel_by_shape` would have: a
    calibration that lands after a seed (at 50 Hz, 2 s of labels are 100 frames) would otherwise start with
    no layout trusted. `observe` counts each given frame it checks the same way.

    Every frame's segments are registered in one batch, then folded in frame order: one frame at a time
    (~80 us each), the 60 frames of a 240-frame history held up the frame that took a calibration by 4-8
    ms, the largest part of a subject scan's p99 (three subjects' calibrations taken 0.45 s apart)."""
    slots = _layout_slots(model, st)
    if slots is None:
        return
    frames = history_m[::SHAPE_EVERY_FRAMES]
    seg = np.maximum(model.marker_segment, 0)  # (slots exclude segment -1)
    f_of, members = np.nonzero(np.isfinite(frames[:, :, 0]) & slots)  # (frame-major, markers ascending)
    counts = np.zeros((len(frames), N_SEGMENTS), int)
    np.add.at(counts, (f_of, seg[members]), 1)
    checked = counts >= SHAPE_MIN_LABELED
    fr, ks = np.nonzero(checked)  # the rows: each frame's checked segments, ascending
    if len(fr) == 0:
        return
    on = checked[f_of, seg[members]]
    f_of, members = f_of[on], members[on]
    key = f_of * N_SEGMENTS + seg[members]
    order = np.argsort(key, kind="stable")  # (a segment's markers stay ascending, as `_layout_fits` has them)
    f_of, members, key = f_of[order], members[order], key[order]
    row = np.searchsorted(fr * N_SEGMENTS + ks, key)
    n_lab, rms, typical = _registered_rows(model, members, frames[f_of, members], row, len(fr))
    fits = rms <= _fit_tolerance(n_lab, typical)[1]
    bounds = np.flatnonzero(np.diff(fr)) + 1
    for rows in np.split(np.arange(len(fr)), bounds):
        _count_layout_fits(st, ks[rows], fits[rows])


def _relabel_by_shape(model: SubjectModel, st: TrackState, points: np.ndarray, point_index: np.ndarray,
                      cur: np.ndarray) -> np.ndarray:
    """Permute the labels within a segment when its calibrated marker layout says they are permuted.
    In place; returns the markers whose point changed. (Given labels, `observe`, only count how often
    each segment's labels fit its layout, `learn_layout_trust`: a layout trusted by the end of a seed can
    undo a swap right after it; a tennis player's wrist labels swapped in the serve, 0.4 s after the
    seed, and stayed swapped for 40 frames while the layout earned its trust.)

    Markers of one segment keep their offsets; a wrist-and-finger triad or a foot's markers permuted by a
    fast pass or a re-acquisition after occlusion keep being tracked permuted, and the long-run partner
    distances absorb it (their spread grows until nothing looks wrong). The layout does not: on 135_02
    the true labels of a forearm fit it to ~11 mm RMS, any permutation of them to 30-80 mm, every frame.
    So each segment's labeled points are registered (Kabsch) onto the offsets of the markers they carry,
    and, where that fits poorly, onto every permutation of their labels, and every assignment that hands
    a just re-acquired marker's point to one of the segment's unlabeled markers (135_02 at L3: the ankle
    marker came back on the fifth metatarsal's point, both hidden for a second, and stayed there)."""
    m = len(point_index)
    changed = np.zeros(m, bool)
    labeled = point_index >= 0
    seg = model.marker_segment
    slots = _layout_slots(model, st)
    if slots is None:
        return changed
    layout = model.layout_offsets_m
    counts = np.bincount(seg[labeled & slots], minlength=int(seg.max()) + 1)
    ks = np.flatnonzero(counts >= SHAPE_MIN_LABELED)
    if len(ks) == 0:
        return changed
    members, row, n_lab, rms0, typical = _layout_fits(model, cur, labeled & slots, ks)
    can_clear, tol = _fit_tolerance(n_lab, typical)
    tight = typical <= SHAPE_CLEAR_LAYOUT_M
    fits = rms0 <= tol
    whole = np.bincount(seg[slots], minlength=int(seg.max()) + 1)[ks] == n_lab
    confirmed = np.zeros(N_SEGMENTS, bool)  # (a lookup: np.isin cost 70-90 us here, a tenth of the check)
    confirmed[ks[fits & whole & (n_lab >= SETTLED_MIN_LABELS)]] = True
    st.settled |= confirmed[seg] & labeled & slots  # (slots: assigned markers only, no segment -1)
    if st.shape_votes:
        for k in ks[fits]:
            st.shape_votes.pop(int(k), None)
    # every permutation of every misfitting segment's labels, registered in one batch (padded to the
    # widest segment): one call instead of one per segment, which cost more than the arithmetic
    flagged = np.flatnonzero(~fits)
    groups = {r: members[row == r] for r in flagged}
    # each segment's labeled slots, then its unlabeled ones: a marker re-acquired on another's point (the
    # ankle marker on the fifth metatarsal's, which was hidden too) is put back by handing its point to the
    # unlabeled marker whose place in the layout it is
    spare = {r: np.flatnonzero(~labeled & slots & (seg == ks[r])) for r in flagged}
    slot_of = {r: np.concatenate([groups[r], spare[r]]) for r in flagged}
    proposals = {}
    # where each marker is, or was last: a label's jump is measured from there
    where = np.where(np.isfinite(cur), cur, st.pos_m)
    for r in flagged:
        lab, slot = groups[r], slot_of[r]
        maps = _relabellings(len(lab), len(slot))
        # every relabelling of the segment scored at once (a compiled loop, `kernels.relabel_candidates`):
        # its fit to the layout, and whether it is blocked. A relabelling trades labels between neighbours
        # (a wrist triad, a foot's markers): labels that would jump across the body tell of a layout
        # calibrated wrong (a seed lying still), not of a permutation. A permutation moves a label at most
        # across its segment (SHAPE_MAX_JUMP_M: a foot's heel to toe; at 0.2 m a tennis player's left foot
        # stayed permuted for 8 s); a label handed to an unlabeled marker, whose place is only known from
        # where it was last, less far (SHAPE_MAX_HANDOVER_M: at 0.3 m a thigh marker calibrated onto a
        # hanging forearm was handed to the finger marker, 85_12 at L3), and only from a re-acquisition
        # still on probation (a marker tracked all along is not suspected of sitting on another's point,
        # short of overwhelming evidence: `_overwhelming_handovers`).
        rms, blocked = kernels.relabel_candidates(layout, cur, where, st.provisional, lab, slot, maps,
                                                  SHAPE_MAX_HANDOVER_M, SHAPE_MAX_JUMP_M)
        if len(lab) >= SHAPE_CLEAR_MIN_LABELS and rms0[r] >= SHAPE_SETTLED_HANDOVER_MISFIT_M:
            blocked &= ~_overwhelming_handovers(st, lab, slot, maps, rms, blocked, tol[r], where)
        fits[r] = rms.min() < SHAPE_GOOD_RMS_M
        # a relabelling the layout itself is symmetric under (a square cluster plate turned by 90 degrees,
        # two markers equidistant from the rest) cannot be told from the identity: never taken, unless the
        # segment's joint tells them apart (`_mirror_by_joint`)
        key = slot.tobytes() + bytes([len(lab)])  # the layout's own symmetries: once per set of slots
        symmetric_rms = st.shape_symmetry.get(key)
        if symmetric_rms is None:
            if len(st.shape_symmetry) > 256:
                st.shape_symmetry.clear()
            ones = np.ones(maps.shape, bool)
            symmetric_rms = st.shape_symmetry[key] = _kabsch_rms(layout[slot[maps]], np.broadcast_to(layout[lab], maps.shape + (3,)), ones)
        # a relabelling that moves the layout's markers less than SHAPE_DISTINCT_M is taken only on clear
        # evidence: the labels misfit the layout by about that move, and the relabelled ones fit it as tightly
        # as in calibration (a toe label on the fifth metatarsal's point, 11 mm apart in the foot's layout:
        # 10 mm misfit, 0.4 mm relabelled; 85_12 at L2). Not with two labels: they match one distance, and a
        # head band's sides and diagonals offer several.
        clear = (
            can_clear[r] & (tight[r] | (maps >= len(lab)).any(1)) & (symmetric_rms >= SHAPE_CLEAR_MIN_M)
            & (rms0[r] >= SHAPE_CLEAR_SHARE * symmetric_rms)
            & (rms <= max(SHAPE_CLEAR_FIT_M, 2.0 * typical[r]))
        )
        unseen = (symmetric_rms < SHAPE_DISTINCT_M) & ~clear  # relabellings the layout cannot tell
        mirror = _mirror_by_joint(model, st, ks[r], lab, slot, maps, cur, unseen & ~blocked & (rms < SHAPE_GOOD_RMS_M))
        if mirror is not None:
            proposals[r] = slot[maps[mirror]]
            continue
        fitting = np.where(unseen, np.inf, rms)  # blocked or not
        fitting[0] = np.inf
        rms = np.where(blocked, np.inf, fitting)
        best = int(np.argmin(rms))
        # (one taken on clear evidence must also stand out: two that fit alike leave it open which)
        rivals = np.count_nonzero(rms < 2.0 * rms[best] + 0.001)
        unique = rivals <= 1 or symmetric_rms[best] >= SHAPE_DISTINCT_M
        # Two labels match one distance, which their swap keeps: every relabelling of them ties with its
        # swap, and a block on one of the two for a label's jump from where a marker was last seen (stale
        # after a long occlusion) used to pick the other (a tennis player's toe label went to the ankle's
        # point and the ankle's to the toe's, for 4 s). Such a tie is told apart by the segment's joint,
        # failing that by the least change (the one relabelling that moves fewest labels, if not blocked),
        # or left alone. (A block for handing over the point of a label tracked all along stands: that label
        # is not suspect.) (Dev suite, 18 realizations: L3 97.932 -> 97.959 %, L2 unchanged, with the joint
        # alone; 97.977 % with the least change, L2 99.219 %, and an HDM05 run whose fifth metatarsal label
        # sat 7 s on the heel's point put back. For segments of any number of labels L3 gained less,
        # 97.946 %, and the head's near-square layout kept a swap twice as long on 85_12.)
        tied = np.flatnonzero(fitting < 2.0 * rms[best] + 0.001) if len(lab) == 2 else np.zeros(0, int)
        tied = tied[~((maps[tied] >= len(lab)) & (st.provisional[lab] <= 0)).any(1)]
        if len(tied) > 1:
            joint_fit = _joint_fits(model, st, ks[r], lab, slot, maps, tied, cur)
            order = np.argsort(joint_fit)
            if joint_fit[order[0]] <= COMPLETE_WRONG_PAIR_JOINT_M and joint_fit[order[1]] >= 2.0 * joint_fit[order[0]] + SHAPE_CLEAR_MIN_M:
                best = int(tied[order[0]])
                unique = not blocked[best]
            else:
                moves = (slot[maps[tied]] != lab).sum(1)
                least = tied[moves == moves.min()]
                if len(least) == 1 and not blocked[least[0]]:
                    best, unique = int(least[0]), True
                elif blocked[tied].any():
                    unique = False
        take = unique and rms[best] < min(SHAPE_GAIN * rms0[r], SHAPE_GOOD_RMS_M) and symmetric_rms[best] > 2.0 * rms[best]
        if take and ks[r] in BENDING_SEGMENTS and (maps[best] >= len(lab)).any():  # (see BENDING_SEGMENTS)
            take = rms[best] <= tol[r]
        if take and ks[r] in TWISTING_SEGMENTS and symmetric_rms[best] < SHAPE_DISTINCT_M:  # (see TWISTING_SEGMENTS)
            joint_fit = _joint_fits(model, st, ks[r], lab, slot, maps, np.array([0, best]), cur)
            take = joint_fit[1] <= joint_fit[0]
        if take:
            proposals[r] = slot[maps[best]]
        else:
            st.shape_votes.pop(int(ks[r]), None)
    # A layout to be trusted fits the labels, or a permutation of them, on most checks; one that seldom
    # does was calibrated wrong (from a pose that hid which markers move together): it is left alone.
    share = _count_layout_fits(st, ks, fits)
    trusted = (share >= SHAPE_TRUSTED_SHARE) & (st.shape_checks[ks] > SHAPE_MIN_CHECKS)
    for r, new_labels in proposals.items():
        if not trusted[r]:
            continue
        lab = groups[r]
        # the same relabelling on SHAPE_CONFIRM checks running: one frame's loose marker is no reason
        moves = tuple(sorted((int(a), int(b)) for a, b in zip(lab, new_labels) if a != b))
        n_votes = st.shape_votes.get(int(ks[r]), ((), 0))
        n_votes = n_votes[1] + 1 if n_votes[0] == moves else 1
        st.shape_votes[int(ks[r])] = (moves, n_votes)
        if n_votes < SHAPE_CONFIRM:
            continue
        del st.shape_votes[int(ks[r])]
        proposed = point_index.copy()
        proposed[lab] = -1
        proposed[new_labels] = point_index[lab]
        moved = slot_of[r][proposed[slot_of[r]] != point_index[slot_of[r]]]
        if st.settled[moved].any():
            continue
        if _partners_object(st, points, cur, labeled, proposed, moved):
            continue
        point_index[moved] = proposed[moved]
        changed[moved] = True
    if changed.any():
        cur[changed] = _gather(points, point_index)[changed]
    return changed


def _trusted_markers(model: SubjectModel, cur: np.ndarray, labeled: np.ndarray, skel_pred: np.ndarray | None,
                     rms: float) -> np.ndarray:
    """(M,) bool: markers the fit may place. All when its RMS residual is under SKELETON_TRUSTED_RMS_M; else
    those of segments with at least three labeled markers this frame, which the fit (carried forward to
    this frame) places within it among themselves. A model that cannot follow part of the body (shoulder
    markers on the torso with the arms overhead, 10-20 cm off in a tennis serve) leaves the fit's RMS at
    20-100 mm while the serving forearm's markers sit within 1-2 cm of their fitted places: its hidden
    wrist marker, 2-3 cm from its fitted place, stayed unlabeled for 38 frames (two players at L2, seed 3).
    Two labeled markers leave the segment's turn about their line free, and a symmetric wrist pair fits
    its swap as well (with two, 135_02 at L3 lost 0.2 % to long wrist swaps).
    (Dev suite, 18 realizations: L2 99.317 -> 99.322 %, L3 98.524 -> 98.533 %; two players at L2 99.41 ->
    99.44 %. A segment held to 10 or 25 mm instead: L2 99.319 / 99.318 %, L3 98.535 / 98.537 %, against
    99.324 / 98.540 % at 15 mm, with the later changes.)"""
    m = model.n_markers
    if rms < SKELETON_TRUSTED_RMS_M:
        return np.ones(m, bool)
    if skel_pred is None:
        return np.zeros(m, bool)
    seg = np.maximum(model.marker_segment, 0)
    err2 = np.sum((cur - skel_pred) ** 2, axis=1)
    seen = labeled & np.isfinite(err2)
    n = np.bincount(seg[seen], minlength=N_SEGMENTS)
    sse = np.bincount(seg[seen], err2[seen], minlength=N_SEGMENTS)
    ok = (n >= 3) & (sse < SKELETON_TRUSTED_RMS_M**2 * np.maximum(n, 1))
    return ok[seg] & (model.marker_segment >= 0)


def _assign(pred: np.ndarray, gates: np.ndarray, points: np.ndarray, cand: np.ndarray):
    """Hungarian assignment of markers (rows of pred, gated) to candidate points.

    Returns (rows, point_idx, contested): contested[k] is True when pair k was a choice — its marker had
    another point in its gate, or its point was in another marker's gate — which is where swaps and
    ghosts slip in, so only those need the (costlier) rigid check."""
    rows, cols, cost, n_row, n_col = kernels.gated_pairs(pred, gates, points, cand)
    if cost.shape[0] == 0:  # no choice to make: no Hungarian solve
        return rows, cols, np.zeros(len(rows), bool)
    r, c = linear_sum_assignment(cost)  # (only markers and points with a pair in the gates: a small problem)
    return kernels.assigned(rows, cols, cost, n_row, n_col, r, c)


def step(
    model: SubjectModel,
    st: TrackState,
    points: np.ndarray,
    free: np.ndarray,
    t_ns: int,
    config: EngineConfig,
    solver=None,
    defer: bool = False,
) -> tuple[TrackState, StepResult]:
    """Label one frame for one subject. `points` (N, 3) finite; `free` (N,) marks points no other subject
    claimed. Mutates and returns `st` (the registry owns it; callers never share a state). With `defer`,
    the labels are returned before the layout check (8.), the state update and the solve launch: `finish`
    does those (the daemon publishes the labels first; timed on 135_02 at L2, they are ~0.13 ms of a
    frame's ~0.4 ms on average, ~0.25 ms more on a layout-check frame)."""
    collect(model, st)
    m = model.n_markers
    dt = min(max((t_ns - st.last_t_ns) * 1e-9, 1e-4), 0.5) if st.frames or st.last_t_ns else 1.0 / 120
    taken = ~free
    if st.last_t_ns and (t_ns - st.last_t_ns) * 1e-9 > LOST_AFTER_GAP_S:
        st.labeled[:] = False  # the frames paused: no track is current, the subject is looked for (step 4)

    # 1. NNT: markers labeled last frame, predicted from their velocity and acceleration (which holds for
    #    a frame step, not across dropped frames), matched inside gates that widen with their speed.
    pred_track, speed, gates = kernels.track_predictions(st.pos_m, st.vel_m_s, st.acc_m_s2, st.labeled, dt,
                                                         dt < 1.5 * st.acc_dt_s, config.nnt_gate_m)
    rows, cols, contested = _assign(pred_track, gates, points, free)
    taken[cols] = True
    # a label needs the rigid check when it was a choice, or when its point is not where the marker was
    # heading (a ghost caught in the gate as the marker vanished); a full check every CHECK_EVERY frames
    # (check: the markers step 2 checks)
    point_index, cur, labeled, check = kernels.track_labels(points, rows, cols, contested, pred_track, speed, dt, m,
                                                            CHECK_RESIDUAL_M, st.ever_seen,
                                                            st.frames % CHECK_EVERY_FRAMES, CHECK_EVERY_FRAMES)
    # labels tracking carried on with no other marker's point in their gate, in a step short of half the
    # way to the nearest other label (a serving arm's labels slid one marker down the chain, each taking
    # the next one's point, none with a rival in its gate) (SETTLED_MIN_LABELS)
    carried = kernels.carried_labels(point_index, cur, pred_track, gates, speed, dt, SLIDE_SHARE)

    # 2. Predict every marker from its rigid partners; a tracked label its partners disagree with (a swap
    #    of two close markers, a ghost caught while the marker hid) is withdrawn and re-assigned below.
    # (the full checks are spread over frames by marker index, so no frame carries them all: a flat p99)
    rpred, spread, swing = rigid_predictions(st, cur, labeled, check)
    # (bad: a label its partners' prediction withdraws)
    has_rigid, spread0, err, bad = kernels.rigid_check(cur, rpred, spread, swing, labeled, RIGID_MAX_SWING_M,
                                                       config.rigid_check_m)
    changed = _unswap(point_index, cur, rpred, err, config.rigid_check_m)
    if st.frames % REPAIR_EVERY_FRAMES == REPAIR_EVERY_FRAMES // 2:
        _repair_by_distances(st, point_index, cur, points, ~taken)
        taken = ~free
        taken[point_index[point_index >= 0]] = True
        changed = True
    if changed:  # (else every label and its error stand as computed)
        labeled = point_index >= 0
        _, _, err, bad = kernels.rigid_check(cur, rpred, spread, swing, labeled, RIGID_MAX_SWING_M,
                                             config.rigid_check_m)
    if bad.any():  # (few: computed on those only)
        rows = np.flatnonzero(bad)
        tol = config.rigid_check_m + 4.0 * spread0[rows]
        bad[rows] = err[rows] > tol + RIGID_LOOSE_K * _partner_sigma(st, labeled, rows)
    # A re-acquired label is on probation: its distances to its partners are held to the long-run norm for
    # PROBATION_FRAMES, so a wrong re-acquisition cannot become its own reference and persist.
    # (and the probation and layout-hold counts move on a frame)
    wrong, st.provisional, st.layout_hold = kernels.probation(st.partners, st.dist_n, st.dist_mean_m, st.dist_var_m2, cur,
                                                              labeled, st.provisional, st.layout_hold, Z_SUSPECT)
    bad |= wrong
    if bad.any():
        taken[point_index[bad]] = False
        point_index[bad] = -1
        labeled = point_index >= 0
        cur[bad] = np.nan
    missing = ~labeled & st.ever_seen

    # 3. The skeleton's word on this frame: the latest fit (launched on an earlier frame's final labels and
    #    computed while they were published), carried forward at its markers' velocity, if it is recent.
    skel_pred = _skeleton_now(st, t_ns, dt) if model.has_skeleton else None
    residual = st.fit_rms_m
    if skel_pred is not None and residual < 0.5 * config.reject_residual_m:
        # two labels that crossed where no partners could tell (a mirror-symmetric pair, such as the two
        # wrist markers, keeps every distance): each sits where the skeleton puts the other
        err_s = kernels.label_errors(cur, skel_pred, labeled & (st.layout_hold <= 0))  # (see SHAPE_HOLD_FRAMES)
        _unswap(point_index, cur, skel_pred, err_s, config.rigid_check_m)

    # 4. Re-acquire occluded markers (Hungarian on predictions, gated).
    coast = st.pos_m + st.vel_m_s * dt * 0.5
    # Markers placed by rigid partners that put them far from the skeleton, where the fit has a word on
    # the segment (it is observed, or held between an observed parent and child; a foot back before its
    # leg is where the fit left it, and the segment search finds it). Partners across a joint learned while
    # it held still (an upper-arm marker's torso partners in a standing seed) agree among themselves and
    # place it where the arm was (24 cm off after a tennis serve, for a second); partners on its own
    # segment, when its last labeled point was another marker's (a serving forearm's marker, labeled on the
    # elbow's point as the arm whipped past, was placed 42 cm off for 0.7 s). The latest fit judges, however
    # old (the solve is skipped while partners place every hidden marker): these launch one, and are
    # searched for.
    # (computed on the few hidden markers partners place, not on all: it runs on most frames)
    stale = np.zeros(m, bool)
    ref = skel_pred if skel_pred is not None else st.skel_pred_m
    if ref is not None:
        seg = model.marker_segment
        far = kernels.far_from_fit(rpred, ref, missing & has_rigid, labeled, st.partners, seg,
                                   SAME_SEGMENT_DISAGREE_M, CROSS_JOINT_DISAGREE_M)
        if far.any():
            observed = _observed_segments(seg, labeled)
            child_seen = np.zeros(N_SEGMENTS, bool)
            child_seen[_PARENTS[observed & (_PARENTS >= 0)]] = True
            held = observed | (child_seen & (_PARENTS >= 0) & observed[np.maximum(_PARENTS, 0)])
            stale[far] = held[np.maximum(seg[far], 0)]
    # Rigid partners place a hidden marker, in a gate that widens with their misfit: when a well-fitting
    # skeleton can take over from loose partners (below), not beyond MAX_GATE_FACTOR (loose partners place
    # a marker poorly); with a skeleton, never beyond MAX_RIGID_GATE_FACTOR. The skeleton speaks for
    # markers with no rigid partners in view, and for those whose partners have moved against each other
    # since (spread), or that they place far from it (above), when the skeleton itself fits well. A marker
    # long hidden with its neighbours left its segment unobserved: the fit has kept that segment where it
    # was, so its gate widens with the time hidden (the distance check below and probation keep ghosts out).
    trusted = _trusted_markers(model, cur, labeled, skel_pred, residual)
    cap = np.inf
    if skel_pred is not None and residual < SKELETON_TRUSTED_RMS_M:
        cap = MAX_GATE_FACTOR * config.reacquire_gate_m
    if model.has_skeleton:
        cap = min(cap, MAX_RIGID_GATE_FACTOR * config.reacquire_gate_m)
    pred_missing, gate_missing, use_skel = kernels.reacquire_gates(
        rpred, has_rigid, spread0, stale, missing, rpred if skel_pred is None else skel_pred, skel_pred is not None,
        trusted, st.hidden_frames, dt, config.reacquire_gate_m, cap, LOOSE_SPREAD_M,
        HIDDEN_WIDEN_S, MAX_HIDDEN_GATE_FACTOR)
    subject_lost = np.count_nonzero(labeled) < 4
    st.lost_frames = st.lost_frames + 1 if subject_lost else 0
    if subject_lost:
        # Lost (full occlusion, a restart from saved state, a subject that left the volume): look for the
        # subject's last known marker cloud in the unclaimed points nearby, registered rigidly (it came
        # back walking, elsewhere, turned); failing that, for every marker where it was last, coasting.
        # A search costs 2-8 ms: after RELOCATE_EAGER_FRAMES it runs on every RELOCATE_EVERY_FRAMES-th frame
        # only, so a subject that left the volume does not slow every frame of the others for as long as
        # it stays away.
        searching = st.lost_frames <= RELOCATE_EAGER_FRAMES or st.frames % RELOCATE_EVERY_FRAMES == 0
        found = _relocate(st, points, ~taken, RELOCATE_GATE_FACTOR * config.reacquire_gate_m) if searching else None
        trunk = np.isin(model.marker_segment, TRUNK_SEGMENTS)
        if searching and found is None and model.has_skeleton and (trunk & st.ever_seen).sum() >= 4:
            # the limbs moved too much to carry the whole cloud: the trunk alone
            found = _relocate(st, points, ~taken, config.reacquire_gate_m, RELOCATE_TRUNK_SHARE, trunk)
        if found is not None:  # only what the registration places well: the fit then finds the limbs
            # (from their pose before the subject left: their gates start narrow again, not widened by
            # the time away)
            st.hidden_frames[:] = 0
            use = missing & np.isfinite(found[:, 0])
            pred_missing[use] = found[use]
            gate_missing[use] = RELOCATE_GATE_FACTOR * config.reacquire_gate_m
        else:
            use = missing & ~np.isfinite(pred_missing[:, 0])
            pred_missing[use] = coast[use]
            gate_missing[use] = config.reacquire_gate_m
    reacquired = np.zeros(m, bool)

    def accept(rows, cols, segment_rule: bool):
        """Take re-acquisitions (rows -> cols) but those their rigid partners' distances refuse and, with
        segment_rule, those `_unsure_on_unseen_segment` holds back."""
        point_index[rows] = cols
        cur = _gather(points, point_index)
        wrong = distance_misfit(st, cur, point_index >= 0, rows)[rows] > Z_SUSPECT
        if segment_rule:
            wrong |= _unsure_on_unseen_segment(model, labeled, rows, cur, use_skel, st.ever_seen, skel_pred,
                                               _norm(st.vel_m_s) * st.hidden_frames * dt)
        point_index[rows[wrong]] = -1
        rows, cols = rows[~wrong], cols[~wrong]
        reacquired[rows] = True
        fresh = rows[st.provisional[rows] <= 0]  # (one re-acquired again on probation keeps the first's)
        st.snap_kept_m[fresh] = st.snap_m[fresh]
        st.provisional[rows] = PROBATION_FRAMES
        taken[cols] = True
        return point_index >= 0, _gather(points, point_index)

    # Markers neither the fit nor their partners can place, unlabeled a few frames though in view, are
    # looked for first, by registering their segment around its joint: markers the fit cannot place (a
    # hand flicked while hidden is found where the fit never looks), and every marker of a segment none of
    # whose markers is labeled. Such a segment (a foot back from an occlusion) moved unseen: the fit and
    # its partners across the joint both keep it where it was, and the Hungarian, left to itself, took
    # the toe marker's point for the fifth metatarsal and so on (135_02 at L3).
    searched = np.zeros(m, bool)  # found where the fit does not look: the fit's word on them is void
    search_due = st.frames % SEARCH_EVERY_FRAMES == 0 or st.search_waits
    st.search_waits = False
    if model.has_skeleton and st.skel_pred_m is not None and search_due:
        seg = model.marker_segment
        observed = _observed_segments(seg, labeled)
        lost = ~labeled & st.ever_seen & (st.hidden_frames >= SEARCH_LOST_FRAMES) & (seg >= 0)
        lost &= ~has_rigid | (spread0 > LOOSE_SPREAD_M) | ~observed[np.maximum(seg, 0)] | stale
        # the search hangs the segments from their joints where the last fit put them: a fit some frames
        # old (solves skipped) misplaces a fast limb's joint, and a serving arm's forearm searched around it
        # took the other hand's points (tennis at L3). Then a solve is launched on this frame and the search
        # waits for it, one frame; the lost markers wait too.
        if lost.any() and (t_ns - st.skel_t_ns) * 1e-9 > SEARCH_FIT_AGE_FRAMES * dt:
            st.search_waits = True
            gate_missing[lost] = 0.0  # nor are they taken one by one from the stale predictions meanwhile
        elif lost.any():
            found = _search_segments(model, st, points, ~taken, labeled, cur, lost)
            if found:
                labeled, cur = accept(np.array(list(found)), np.array(list(found.values())), segment_rule=False)
                searched[list(found)] = labeled[list(found)]
                gate_missing[labeled] = 0.0
    rows, cols, _ = _assign(pred_missing, gate_missing, points, ~taken)
    if len(rows):
        labeled, cur = accept(rows, cols, segment_rule=model.has_skeleton)
    if skel_pred is not None and trusted.any():
        # A second opinion: a marker its partners placed where no point is (partners across a joint that
        # bent while it hid) is looked for where a well-fitting skeleton puts it, inside a narrower gate.
        # Not on the frame it vanished (hidden_frames 0): a ghost born beside it would be taken.
        # (dev suite, 8 files x L2/L3, seeds 0-5: 135 such labels right, 3 wrong; a 45 mm gate: 178 / 19)
        # Where the fit is trusted (`_trusted_markers`; per marker rather than on the fit's RMS: dev suite,
        # 18 realizations, L2 99.322 -> 99.324 %, L3 98.533 -> 98.536 %).
        second = ~labeled & st.ever_seen & has_rigid & ~use_skel & (st.hidden_frames >= 1) & trusted
        if second.any():
            gate = np.where(second, SECOND_OPINION_GATE_M, 0.0)
            rows, cols, _ = _assign(np.where(second[:, None], skel_pred, np.nan), gate, points, ~taken)
            if len(rows):
                labeled, cur = accept(rows, cols, segment_rule=True)
    if not model.has_skeleton and search_due and not subject_lost:
        # no skeleton (a seed taken lying down): a cluster hidden whole, which its partners across the
        # joint place where it was, is found by its own layout (`_search_rigid_groups`)
        lost = ~labeled & st.ever_seen & (st.hidden_frames >= SEARCH_LOST_FRAMES)
        if lost.sum() >= GROUP_MIN_PLACED:
            found = _search_rigid_groups(st, points, np.flatnonzero(~taken), labeled, cur, lost)
            if found:
                labeled, cur = accept(np.array(list(found)), np.array(list(found.values())), segment_rule=False)

    # 5. Reject labels the model disagrees with.
    if skel_pred is not None and residual < 0.5 * config.reject_residual_m:
        # the model's word counts only where no rigid partners can speak for a marker
        err = kernels.label_errors(cur, skel_pred, labeled)
        bad = labeled & check & ~has_rigid & (err > config.reject_residual_m) & ~searched
        if bad.any():
            point_index[bad] = -1
            labeled = point_index >= 0
            cur[bad] = np.nan

    # 6. Where the state will put hidden markers (the bookkeeping below: their partners' prediction, else the
    #    fit's, else coasting), and this frame's predictions (the fit's where there is one, for all markers).
    # 7. Launch (below) the skeleton fit on the final labels when a hidden marker is left that its rigid
    #    partners cannot place (the fit will place it from the next frame on), or when the skip budget is spent.
    #    (Loose partners ask for a fit only when the whole fit is trusted, not where `_trusted_markers` trusts
    #    it per segment: that launched solves on 45 % of 135_02's frames at L2 instead of 39 %, and scored
    #    less, dev suite L3 98.540 against 98.554 %, L2 99.324 against 99.323 %.)
    source, fallback, predicted, unplaced = kernels.frame_outcome(
        point_index, reacquired, cur, has_rigid, rpred, coast, rpred if skel_pred is None else skel_pred,
        skel_pred is not None, st.ever_seen, spread0, stale, LOOSE_SPREAD_M,
        np.full(m, residual < SKELETON_TRUSTED_RMS_M))
    launch = False
    if model.has_skeleton and solver is not None:
        if unplaced or st.search_waits or st.skipped >= min(config.max_skip_frames, config.max_skip_s / dt - 1e-6):
            launch = True
            st.skipped = 0
        else:
            st.skipped += 1
    solved = launch and _launchable(labeled)

    def bookkeeping():
        # 8. Labels permuted within a segment (a wrist triad after a fast pass or a re-acquisition) are put
        #    back in the order the segment's marker layout says. Not before publishing: a relabelling waits
        #    for SHAPE_CONFIRM checks anyway (four frames apart), so one frame more costs little, and these
        #    checks are the costliest step of a frame (~0.25 ms on every SHAPE_EVERY_FRAMES-th). The state
        #    takes the new labels; this frame's published ones stay as they were. Points claimed meanwhile
        #    by subjects stepped after this one (`free` is the engine's, updated in place) are not free.
        idx, now = point_index.copy(), cur.copy()
        relabeled = np.zeros(m, bool)
        st.settled &= (idx >= 0) & (idx == carried)  # a label any other step moved, or none: unsettled
        if model.has_skeleton and st.frames % SHAPE_EVERY_FRAMES == 0:
            relabeled = _relabel_by_shape(model, st, points, idx, now)
            relabeled |= _complete_by_free_point(model, st, points, ~taken & free, idx, now)
            relabeled |= _complete_lone_label(model, st, points, ~taken & free, idx, now)
            relabeled |= _reseat_outliers(model, st, points, ~taken & free, idx, now)
            if relabeled.any():
                # the last fit followed the permuted labels (it turned the forearm half a turn to match):
                # its word on these markers is void until a fit on the new labels (launched here) comes back,
                # and its swaps of them for a while after (SHAPE_HOLD_FRAMES)
                st.skel_pred_m = None
                st.layout_hold[relabeled] = SHAPE_HOLD_FRAMES
        st.labeled &= ~relabeled  # a relabelled marker's velocity is its old one, not the jump between tracks
        # A re-acquired label the checks took off its point (another marker's) has had its partners'
        # snapshot retaken there on every frame since: it would place the marker on that point from now on,
        # 8-10 cm from where it is (a serving wrist label carried onto the finger's point, handed to the
        # finger marker: the wrist, back in view, stayed unlabeled for 30 frames, two players at L2). It
        # gets back the snapshot from before its re-acquisition. (Dev suite, 18 realizations: L3 98.380 ->
        # 98.405 %, precision 98.954 -> 98.969 %, L2 99.314 -> 99.316 %; dropping the snapshot instead, L3
        # 98.400 %; the same for labels the partners' or the model's check withdraws on probation, 98.387 %:
        # those are as often right labels on a fast limb, whose latest snapshot is the better one.)
        undone = relabeled & (idx < 0) & (st.provisional > 0)
        st.snap_m[undone] = st.snap_kept_m[undone]
        final = idx >= 0
        _commit(st, now, final, fallback, t_ns, dt)
        if launch or (relabeled.any() and model.has_skeleton and solver is not None):
            _launch(model, st, solver, now, final, t_ns)
            st.skipped = 0

    st.unfinished = bookkeeping
    if not defer:
        finish(st)
    return st, StepResult(
        source=source,
        point_index=point_index.astype(np.int32),
        predicted_m=predicted,
        solved=solved,
        iterations=st.fit_iterations,
        residual_m=st.fit_rms_m,
        positions_m=cur,
    )


def observe(
    model: SubjectModel, st: TrackState, cur: np.ndarray, t_ns: int, config: EngineConfig, solver=None
) -> tuple[TrackState, StepResult]:
    """Take given labels as truth (a capture system's own labels, an operator's corrections): `cur` (M, 3)
    holds the labeled positions, NaN where a marker has no label. Keeps every statistic `step` keeps."""
    collect(model, st)
    dt = min(max((t_ns - st.last_t_ns) * 1e-9, 1e-4), 0.5)
    labeled = np.isfinite(cur[:, 0])
    st.settled = labeled.copy()
    missing = ~labeled & st.ever_seen
    rpred, _, _ = rigid_predictions(st, cur, labeled, missing)
    skel_pred = _skeleton_now(st, t_ns, dt) if model.has_skeleton else None
    fallback = np.where(np.isfinite(rpred[:, :1]), rpred, st.pos_m if skel_pred is None else skel_pred)
    if model.has_skeleton and st.frames % SHAPE_EVERY_FRAMES == 0:
        learn_layout_trust(model, st, cur[None])
    _commit(st, cur, labeled, fallback, t_ns, dt)
    solved = False
    if model.has_skeleton and solver is not None and st.skipped >= min(config.max_skip_frames, 2):
        solved = _launch(model, st, solver, cur, labeled, t_ns)
        st.skipped = 0
    else:
        st.skipped += 1
    source = np.where(labeled, 3, 0).astype(np.int8)
    return st, StepResult(np.full(model.n_markers, -1, np.int32), st.pos_m.copy(), solved, st.fit_iterations, st.fit_rms_m, source, cur)


def _commit(st: TrackState, cur: np.ndarray, labeled: np.ndarray, fallback: np.ndarray, t_ns: int, dt: float) -> None:
    """Fold one frame's labels into the state: positions, velocities, partner statistics, snapshots."""
    # A velocity needs two observations. A re-acquired marker's last position is only a prediction (from
    # partners that may have been hidden too, or coasting): (cur - prediction) / dt would turn the
    # prediction's error into speed, and the next frame's NNT would follow it, through a gate it also
    # widens, onto a neighbour. So a re-acquired marker keeps its last measured velocity (decayed while
    # hidden). Velocities are smoothed lightly against noise, not so much that fast markers lag; an
    # acceleration comes from two measured velocities: at 50 Hz a serving arm's hand turns 4 cm off its
    # constant-velocity path in one frame, onto its neighbour. (A compiled loop: `kernels.commit_motion`.)
    st.pos_m, st.vel_m_s, st.acc_m_s2, st.vel_measured, st.hidden_frames = kernels.commit_motion(
        st.pos_m, st.vel_m_s, st.acc_m_s2, st.vel_measured, st.hidden_frames, st.labeled, cur, labeled, fallback,
        dt, MAX_SPEED_M_S, MAX_ACC_M_S2)
    st.acc_dt_s = dt
    st.labeled = labeled
    st.ever_seen |= labeled
    st.last_t_ns = t_ns
    st.frames += 1
    if labeled.any():
        st.last_labeled_t_ns = t_ns
    if st.frames % 2 == 0:  # the statistics move slowly: every other frame halves their O(M^2) cost
        _update_distances(st, cur, labeled)
    if st.frames % 30 == 0:
        _update_partners(st)
    _snapshot(st, cur, labeled)


def resume(st: TrackState, rows: np.ndarray, positions_m: np.ndarray) -> None:
    """Markers found outside the step (`rows`, at `positions_m` this frame: an automatic subject's trial) are
    tracked from there on the next frame, at rest."""
    st.labeled[rows] = True
    st.ever_seen[rows] = True
    st.pos_m[rows] = positions_m
    st.vel_m_s[rows] = 0.0
    st.acc_m_s2[rows] = 0.0
    st.vel_measured[rows] = False
    st.hidden_frames[rows] = 0


def finish(st: TrackState) -> None:
    """Run the bookkeeping a deferred `step` left (idempotent)."""
    if st.unfinished is not None:
        bookkeeping, st.unfinished = st.unfinished, None
        bookkeeping()


def _launchable(labeled: np.ndarray) -> bool:
    return int(np.count_nonzero(labeled)) >= 4  # fewer cannot hold a pose


def _launch(model: SubjectModel, st: TrackState, solver, cur: np.ndarray, labeled: np.ndarray, t_ns: int) -> bool:
    """Start a Gauss-Newton solve from the current pose on this frame's labels; `collect` takes its result."""
    if not _launchable(labeled):
        return False
    st.pending = (solver.launch(st.t_root_m, st.R_parent_segment, model.joint_offsets_m, model.marker_segment,
                                model.marker_offsets_m, cur, labeled), t_ns)
    return True


def collect(model: SubjectModel, st: TrackState):
    """Finish the fit launched on an earlier frame (waiting for it if need be) and take its pose, its marker
    predictions and their velocity (from the previous fit when it was recent). A failed solve keeps the
    pose: never a frozen or exploding skeleton. Returns the FitResult, or None (nothing pending, failed).
    Idempotent; in place. A deferred step's bookkeeping is done first."""
    finish(st)
    if st.pending is None:
        return None
    pending, t_ns = st.pending
    st.pending = None
    fit = pending.result()
    if not fit.ok or not np.isfinite(fit.residual_rms_m) or len(fit.predicted_m) != model.n_markers:
        st.skel_pred_m = None
        return None
    vel = np.zeros_like(fit.predicted_m)
    gap_s = (t_ns - st.skel_t_ns) * 1e-9
    if st.skel_pred_m is not None and len(st.skel_pred_m) == model.n_markers and 0 < gap_s <= SKELETON_VELOCITY_GAP_S:
        vel = (fit.predicted_m - st.skel_pred_m) / gap_s
        speed = np.linalg.norm(vel, axis=1, keepdims=True)
        vel *= np.minimum(1.0, MAX_SPEED_M_S / np.maximum(speed, 1e-9))
    st.t_root_m, st.R_parent_segment = fit.t_world_root_m, fit.R_parent_segment
    st.fit_rms_m, st.fit_iterations = fit.residual_rms_m, fit.iterations
    st.skel_pred_m, st.skel_vel_m_s, st.skel_t_ns = fit.predicted_m, vel, t_ns
    return fit


def _skeleton_now(st: TrackState, t_ns: int, dt: float) -> np.ndarray | None:
    """The latest fit's marker positions carried forward to t_ns, if that fit is at most ~2 frames old."""
    if st.skel_pred_m is None or st.skel_vel_m_s is None:
        return None
    age_s = (t_ns - st.skel_t_ns) * 1e-9
    if not 0 <= age_s <= 2.5 * dt:
        return None
    return st.skel_pred_m + st.skel_vel_m_s * age_s


def _fit(model: SubjectModel, st: TrackState, solver, cur: np.ndarray, labeled: np.ndarray):
    """One blocking Gauss-Newton solve from the current pose (calibration, refinement); on failure keep
    the pose. Any launched fit is collected first, so it cannot overwrite this one."""
    collect(model, st)
    if labeled.sum() < 4:
        return None
    fit = solver.fit(
        st.t_root_m, st.R_parent_segment, model.joint_offsets_m, model.marker_segment, model.marker_offsets_m, cur, labeled
    )
    if not fit.ok or not np.isfinite(fit.residual_rms_m):
        return None
    st.t_root_m = fit.t_world_root_m
    st.R_parent_segment = fit.R_parent_segment
    st.fit_rms_m, st.fit_iterations = fit.residual_rms_m, fit.iterations
    st.skel_pred_m = None  # a fit of another frame than the last: nothing to carry forward
    return fit
