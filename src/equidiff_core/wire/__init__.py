"""Wire formats: what travels between the nodes and into the bags, each built and checked in one place.

* ``rosmsg``: the message codec (factories, stamps, poses, transforms, joint states, diagnostics)
* ``pointcloud``: the camera clouds and the occupied-voxel cloud (PointCloud2)
* ``chunk``: pose chunks (MultiDOFJointTrajectory), and how they are answered and executed
* ``topics``: every topic name, and the type of each recorded one
"""
