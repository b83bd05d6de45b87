"""wfnn's think server: stores experiences durably, replays them (thinks) and publishes weight snapshots.

Also the live dashboard (a read-only `ViewModel`) and `wfnn-router`, a Zenoh router for robots
and servers on other hosts.
"""

from wfnn_io.launch import tool

main = tool("wfnn_server.cli")
"""`wfnn-server`."""
main_router = tool("wfnn_server.router")
"""`wfnn-router`."""
