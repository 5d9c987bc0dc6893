"""Visits: a landmark's observations split where it went unseen, and the links between them.

A loop closure is a landmark seen again after a long gap. Giving each visit its own position
and tying the visits of one landmark by a robust link factor (``problem``) lets the smoother
drop a loop closure the rest of the data contradict instead of bending the map around it.

Shapes: T steps, K observation rows, V visits, E links, L landmarks.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Visits(NamedTuple):
    """The visits of ``smooth_path(visit_gap=...)`` (``split_visits``) and their links.

    position: (V, 2) smoothed position of each visit; visit_of_obs: (T, K) (-1: none);
    landmark: (V,) the landmark of each visit; links: (E, 2) linked visit pairs;
    link_weight: (E,) final IRLS weight of each link, 1 kept ... 0 dropped (a loop closure
    the data contradict).
    """

    position: np.ndarray
    visit_of_obs: np.ndarray
    landmark: np.ndarray
    links: np.ndarray
    link_weight: np.ndarray


def check_visit_options(visit_gap, link_neighbours=2):
    """ValueError unless ``visit_gap`` and ``link_neighbours`` are integers >= 1 (callers
    that smooth after a long filter run check first, so a bad value costs no run)."""
    for name, value in (("visit_gap", visit_gap), ("link_neighbours", link_neighbours)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1 (steps / visits); got {value!r}")


def split_visits(landmark_of_obs, visit_gap: int, link_neighbours: int = 2):
    """Split each landmark's observations into visits and pair the visits of one landmark.

    A visit is a run of a landmark's observations with no gap of more than ``visit_gap``
    steps. Each visit gets its own position in the least squares; a link factor ties it to
    the ``link_neighbours`` visits of the same landmark before it (so one wrong visit in the
    middle does not cut the chain). A link is a loop closure the filter decided on; giving
    it a redescending loss lets the smoother drop the ones the rest of the data contradict.

    Args:
      landmark_of_obs: (T, K) landmark index per observation, -1 for none.
      visit_gap: steps without an observation of a landmark that end a visit (>= 1).
      link_neighbours: earlier visits each visit is linked to (>= 1).
    Returns:
      visit_of_obs (T, K) visit index (-1 where ``landmark_of_obs`` is -1),
      visit_landmark (V,) the landmark of each visit, links (E, 2) visit pairs (a < b).
    """
    check_visit_options(visit_gap, link_neighbours)
    landmark_of_obs = np.asarray(landmark_of_obs)
    if landmark_of_obs.ndim != 2:
        raise ValueError(f"landmark_of_obs must be (T, K); got shape {landmark_of_obs.shape}")
    t, k = np.nonzero(landmark_of_obs >= 0)
    ids = landmark_of_obs[t, k]
    order = np.lexsort((t, ids))  # by landmark, then time
    ids_sorted, t_sorted = ids[order], t[order]
    starts = np.ones(len(order), bool)
    starts[1:] = (ids_sorted[1:] != ids_sorted[:-1]) | (np.diff(t_sorted) > visit_gap)
    visit_sorted = np.cumsum(starts) - 1
    visit_of_obs = np.full(landmark_of_obs.shape, -1, np.int64)
    visit_of_obs[t[order], k[order]] = visit_sorted
    visit_landmark = ids_sorted[starts]
    # Visits of one landmark are consecutive indices: pair v with v - j when same landmark.
    visit = np.arange(len(visit_landmark))
    links = [np.stack([visit[:-j], visit[j:]], 1)[visit_landmark[:-j] == visit_landmark[j:]]
             for j in range(1, link_neighbours + 1) if j < len(visit)]
    links = np.concatenate(links) if links else np.zeros((0, 2), np.int64)
    return visit_of_obs, visit_landmark, links


def largest_visit(position, visit_of_obs, visit_landmark):
    """(L, 2): each landmark at its visit with the most observations (ties: the earlier).

    Args:
      position: (V, 2) visit positions; visit_of_obs: (T, K) (-1: none); visit_landmark: (V,).
    """
    count = np.bincount(visit_of_obs[visit_of_obs >= 0], minlength=len(visit_landmark))
    order = np.lexsort((-count, visit_landmark))  # by landmark, largest visit first
    first = np.ones(len(order), bool)
    first[1:] = visit_landmark[order][1:] != visit_landmark[order][:-1]
    landmark = np.zeros((int(visit_landmark.max(initial=-1)) + 1, 2))
    landmark[visit_landmark[order][first]] = position[order][first]
    return landmark
