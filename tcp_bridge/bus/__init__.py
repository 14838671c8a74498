"""Execution on the buses: one worker thread per bus, shared reads, fail-fast health,
and typed SDO ports.

A job arrives here fully planned (:mod:`tcp_bridge.plan`); this package decides
only when and on which thread it runs, never what it means.
"""
