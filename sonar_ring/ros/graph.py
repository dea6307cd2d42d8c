"""graph: driver, localiser and mapper in one process and one executor.

The same nodes as the three executables, composed: each hands its ping straight
to the next (:func:`compose`), as rclcpp's intra-process communication does,
so a ping is one executor callback from the driver's input to the map.  Every
topic is still published for RViz, recorders and your nodes, in the order that
gets a ping to RViz first: the driver hands a ping on before it publishes
``echoes``, and the localiser publishes ``markers``, ``landmarks`` and
``landmarks/pairs`` before it hands the ping to the mapper, and
``landmarks/raw`` after.  The nodes take their inputs only from each other, so
feed this process through the driver's source (``source:=topic`` reads
``tof_in``) -- or run the three executables to take ``echoes`` or
``landmarks/pairs`` from elsewhere.  Odometry still comes over DDS.
"""

import itertools

from sonar_ring.ros.driver import Driver
from sonar_ring.ros.localiser import Localiser
from sonar_ring.ros.mapper import Mapper
from sonar_ring.ros.params import ParameterError
from sonar_ring.ros.run import spin

NODES = (Driver, Localiser, Mapper)


def compose(nodes) -> None:
    """Wire ``nodes`` (instances of :data:`NODES`, in that order) so each takes its pings from the one before.

    Raises :class:`~sonar_ring.ros.params.ParameterError` when the driver
    and localiser were given different layouts: handed over
    directly, a ping is not checked against the next node's layout again.
    """
    layouts = {node.get_name(): node.layout.name for node in nodes if hasattr(node, "layout")}
    if len(set(layouts.values())) > 1:
        raise ParameterError(f"layout: the nodes of one process must share one layout, got {layouts}")
    for upstream, node in itertools.pairwise(nodes):
        node.follow(upstream)


def main(args=None) -> None:
    """Run the three nodes, composed, until Ctrl-C or shutdown."""
    spin(*NODES, args=args, setup=compose)


if __name__ == "__main__":
    main()
