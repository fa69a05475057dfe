"""Taught routes (Li et al.): an image sequence taught with odometry, partitioned into nodes,
its loops closed and relaxed, for navigation sessions that follow it. Served under
``/v1/maps/{map_id}/routes``."""
