"""The paper's ROS 1 classes, on the dbml runtime: a port of a DBM node needs few changes.

::

    rospy.init_node("camera")
    pub = DBMPublisher("camera", Image, 1, 16)   # topic, class, min and max frequency (Hz)
    rate = DBMRate(pub)                           # the allocated frequency, like rospy.Rate
    while not rospy.is_shutdown():
        pub.publish(capture())
        rate.sleep()

They share one ``Ros1Transport`` per process (the node started with ``rospy.init_node``, else
one of their own), so parameters live on the real parameter server and topics are real ROS
topics. Importing this package needs rospy (Debian's ``python3-rospy``).
"""

from dbml.ros1.classes import (
    DBMOptimizer,
    DBMPublisher,
    DBMRate,
    DBMSubscriber,
    ros1_transport,
)

__all__ = ["DBMOptimizer", "DBMPublisher", "DBMRate", "DBMSubscriber", "ros1_transport"]
