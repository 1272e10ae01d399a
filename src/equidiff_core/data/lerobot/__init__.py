"""Episode bags -> a LeRobot v3.0 dataset, without LeRobot installed.

* ``export``: the export itself (``export_lerobot``)
* ``layout``: LeRobot's v3.0 layout: path templates, the frame table's schema, statistics
* ``video``: each camera's recorded images matched to the frames and encoded to AV1 mp4
"""
