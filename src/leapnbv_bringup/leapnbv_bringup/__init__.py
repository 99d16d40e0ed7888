"""Launch files, deployed parameters and the graph runner for the LEAP-NBV node set."""
