"""One ping's path from decoded echoes to labelled landmarks, as every node and command runs it.

The localiser node (alone or in ``graph`` and the demo), ``sonar-ring process``
and the map benchmarks all call this module:

* :func:`check_ping` -- the one boundary a ping's arrays cross: the layout it
  names, then :func:`sonar_ring.echoes.screen_ping`; what is refused or dropped
  is counted by reason on a :class:`Counts` (or a node's ``NodeHealth``, which
  has the same two methods).
* :class:`PingStage` -- the localiser's work on a checked ping, after loading
  exactly the compiled kernels it runs (:meth:`PingStage.load_kernels`):
  :func:`sonar_ring.pipeline.localise_ping` then
  :func:`~sonar_ring.pipeline.classify_ping` (:meth:`PingStage.label`); what it
  publishes of a labelled ping, one landmark per echo
  (:meth:`PingStage.publishable`, :func:`~sonar_ring.pipeline.joint_landmarks`);
  all three for one ping (:meth:`PingStage.label_and_publish`) or for many at
  once (:meth:`PingStage.label_and_publish_many`).

A ping's result needs nothing of other pings, so it does not depend on where
the stage runs (a node's callback, a worker process of ``sonar-ring process``).
Nothing here imports ROS: headers are the nodes' business; a ping is named by
its stamp (integer ns) in the counts' details.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from sonar_ring import localise, pipeline, ring_consistency
from sonar_ring.echoes import EchoArrays, screen_ping
from sonar_ring.echoes import load_kernels as load_screening_kernels
from sonar_ring.geometry import Layout
from sonar_ring.landmarks import Landmarks


class Counts:
    """Problems and expected losses counted by reason: the two methods of a node's ``NodeHealth``, without a node.

    ``sonar-ring process``, ``record-sim`` and the benchmarks count with it
    what the nodes report on ``/diagnostics``.
    """

    def __init__(self) -> None:
        self.problems: Counter[str] = Counter()
        self.notes: Counter[str] = Counter()

    def problem(self, reason: str, detail: str = "", count: int = 1) -> None:
        """Count ``count`` bad inputs of ``reason`` (``detail`` is for a node's log line)."""
        if count:
            self.problems[reason] += count

    def note(self, reason: str, count: int = 1) -> None:
        """Count ``count`` expected losses of ``reason`` (no fault: an empty ping, ...)."""
        if count:
            self.notes[reason] += count


def check_ping(echoes: EchoArrays, layout: Layout, counts, stamp: int) -> EchoArrays | None:
    """The usable part of a ping, or None after counting why nothing of it is.

    A ping of another layout (``layout_mismatch``) or that the layout cannot
    read (:func:`sonar_ring.echoes.screen_ping`: rows that do not match, the
    wrong number of receivers, a bad speed of sound) is refused whole; bad rows
    and values are dropped and counted by reason, and the rest of the ping is
    returned.  A ping left without rows is returned empty and noted
    (``empty ping``).

    Parameters
    ----------
    echoes : EchoArrays
        The ping as decoded, N rows.
    layout : Layout
        The sensor the ping must fit.
    counts : Counts or NodeHealth
        Where refusals (``problem``) and expected losses (``note``) are counted.
    stamp : int
        The ping's stamp, ns, to name it in the counts' details.
    """
    if echoes.layout != layout.name:
        counts.problem("layout_mismatch", f"echoes of layout {echoes.layout!r}, expected {layout.name!r}")
        return None
    result = screen_ping(echoes, layout)
    for reason, count in result.problems.items():
        where = f"ping at {stamp // 10**9}.{stamp % 10**9:09d}"
        counts.problem(reason, f"{where}: {result.detail}" if result.detail else where, count)
    if result.echoes is not None and result.echoes.n_echoes == 0:
        counts.note("empty ping")
    return result.echoes


@dataclass(frozen=True)
class PingStage:
    """Localise and label checked pings of one layout with one set of settings.

    Attributes
    ----------
    layout : Layout
        The sensor.
    settings : sonar_ring.pipeline.Settings
        Models, noise and test thresholds (the localiser node's parameters).
    """

    layout: Layout
    settings: pipeline.Settings = pipeline.Settings()

    def load_kernels(self) -> None:
        """Load the compiled kernels this stage runs for its layout now, so the first ping does not wait for them.

        Screening always; the pair models except on a triad (whose landmarks
        come from phase bearing and range); the labelling; the ring's
        consistency test on a ring.
        """
        load_screening_kernels()
        if self.layout.kind != "triad":
            localise.load_kernels()
        pipeline.load_kernels()
        if self.layout.kind == "ring":
            ring_consistency.load_kernels()

    def label(self, echoes: EchoArrays) -> tuple[Landmarks, Landmarks]:
        """A checked ping's hypotheses (valid and not, shape: a row per echo and model) and its labelled landmarks.

        Frames as the ping's: the sensor frame, m.
        """
        hypotheses = pipeline.localise_ping(self.layout, echoes, self.settings)
        return hypotheses, pipeline.classify_ping(self.layout, echoes, hypotheses, self.settings)

    def label_and_publish_many(self, pings: list[EchoArrays]) -> list[tuple[Landmarks, Landmarks, Landmarks]]:
        """:meth:`label_and_publish` of each checked ping, valid hypotheses only, computed in stacked batches.

        Per ping exactly what :meth:`label_and_publish` gives it alone, less its invalid
        hypotheses (:func:`sonar_ring.pipeline.label_pings`).
        """
        return pipeline.label_pings(self.layout, pings, self.settings)

    def label_and_publish(self, echoes: EchoArrays) -> tuple[Landmarks, Landmarks, Landmarks]:
        """:meth:`label` and :meth:`publishable` of one checked ping, the ring's fits computed once.

        The hypotheses, the labelled landmarks and those to publish, as the two give them.
        """
        return pipeline.label_and_publish(self.layout, echoes, self.settings)

    def publishable(self, echoes: EchoArrays, labelled: Landmarks) -> Landmarks:
        """The landmarks to publish of a checked ping labelled ``labelled``: one per echo, joint where it can be.

        :func:`sonar_ring.pipeline.joint_landmarks`: on a ring an echo two or more pairs heard is
        one landmark, the fit over all their receivers; elsewhere ``labelled`` itself.  The
        mapper takes ``labelled``, one independent sighting per echo row.
        """
        return pipeline.joint_landmarks(self.layout, echoes, labelled, self.settings)
