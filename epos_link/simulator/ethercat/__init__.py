"""Simulated EPOS4 drives as EtherCAT slaves (issue 26): see docs/simulator.md, "EtherCAT".

Pure core: frame, esc, sii, coe, pdo, slave, segment. I/O: server (raw socket thread);
drive_app joins a slave to the CiA 402 drive model.
"""
