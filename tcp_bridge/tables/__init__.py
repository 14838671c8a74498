"""PSI spec 3 and 4 as data: the command table, the axis table and its TOML, units,
the per-axis parameter arrays and the state file that keeps them.

Nothing here talks to a drive; :mod:`tcp_bridge.plan` resolves requests against
these tables, :mod:`tcp_bridge.bus` runs what the plan decided.
"""
