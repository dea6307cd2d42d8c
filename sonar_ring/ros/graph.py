"""graph: driver, localiser, classifier and mapper in one process and one executor.

The same nodes as the four executables, without the DDS hops between processes
(messages still go through rclpy's intra-process path of the middleware).
"""

from sonar_ring.ros.classifier import Classifier
from sonar_ring.ros.driver import Driver
from sonar_ring.ros.localiser import Localiser
from sonar_ring.ros.mapper import Mapper
from sonar_ring.ros.run import spin

NODES = (Driver, Localiser, Classifier, Mapper)


def main(args=None) -> None:
    """Run the four nodes until Ctrl-C or shutdown."""
    spin(*NODES, args=args)


if __name__ == "__main__":
    main()
