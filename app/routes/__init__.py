"""Route maps: a taught image sequence with odometry, partitioned and relaxed."""
