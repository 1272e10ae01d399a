"""What every job and node runs on: time, the machine, job reporting, output files, the parent job.

* ``clock``: time in the lab (the wall clock) and in the twin (simulated time)
* ``machine``: what CPU this is, its idle cores, the calling thread's scheduling policy
* ``jobs``: what the core's jobs share with whoever runs them (``JobError``, progress lines)
* ``output_files``: outputs written beside their target and renamed into place (``staged_output``)
* ``parent_job``: which job started this process, and whether it is still there
"""
