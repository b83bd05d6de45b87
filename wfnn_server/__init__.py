"""wfnn's think server: stores experiences durably, replays them (thinks) and publishes weight snapshots.

Also the live dashboard (a read-only `ViewModel`) and `wfnn-router`, a Zenoh router for robots
and servers on other hosts.
"""
