"""Stage 4, network: the plain network loop on the normalised working clouds -> one candidate pose."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from service.icp import NORMAL_NEIGHBOURS
from service.rotation_search import SearchCandidate
from service.stages.normalise import Working

if TYPE_CHECKING:
    from service.registrar import Registrar


@dataclass(frozen=True, eq=False)
class Candidates:
    """Candidate poses between the normalised clouds, best first, and the clouds the network ran on."""

    poses: list[SearchCandidate]
    net_s: np.ndarray  # [Ns'] the caller's source rows the network ran on
    net_t: np.ndarray  # [Nt'] the caller's target rows
    feature_support: int = 0  # matched pairs agreeing with the last pose, a feature candidate (0: none joined)


def network(registrar: Registrar, work: Working, iterations: int, keypoints: int,
            timing: dict[str, float]) -> Candidates:
    """The network's pose from the identity start (records ``timing`` ``encoder``, ``iterations``, ``svd``)."""
    shared = registrar.encoder_takes_neighbours and registrar.knn <= NORMAL_NEIGHBOURS
    graphs = work.working_graphs if shared else None  # the refinement's normals use them too
    net = registrar.run_network(work.src_n, work.tgt_n, iterations, keypoints, timing, graphs=graphs)
    return Candidates([SearchCandidate(net, np.eye(3), net.rotation, net.translation)], work.idx_s, work.idx_t)
