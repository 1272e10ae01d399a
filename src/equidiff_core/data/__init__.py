"""Demonstration data: episode bags written, read and repaired, decoded into training samples, exported.

* ``mcap_writer``, ``mcap_reader``: the one way a bag's MCAP file is written and read (CRCs written and checked)
* ``recording``: the episode writer (one rosbag2 directory per episode)
* ``bags``: reading episode bags, repairing killed or damaged recordings
* ``episode_arrays``: one decoded episode as arrays, its settings, and its packed form on disk
* ``dataset``: training samples from episode bags (the model contract's batch format)
* ``synthetic``: synthetic voxel/action samples that need no twin
* ``lerobot``: episode bags -> a LeRobot v3.0 dataset (``export``, ``layout``, ``video``)
"""
