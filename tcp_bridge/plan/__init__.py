"""A request resolved once against the tables and the axis's state, then planned by one
handler for its kind of command: no I/O here, only the closures the bus runs.
"""
