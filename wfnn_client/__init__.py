"""Robot-side wfnn: `act` on numpy at a fixed tick, the safety layer, learning locally or via servers.

Acting never needs torch: the deep learner's snapshot is acted on in numpy, and torch is
imported only when this process thinks with the deep learner itself. The robots driven here are
simulated: `wfnn_client.sims` is the table of them and imports `sims` (MuJoCo for HyDrA and the
Nomad); a real robot would take a task's place behind the same interface (`sims.base.VecTask`).
"""

from wfnn_io.launch import tool

main = tool("wfnn_client.cli")
"""`wfnn-client`."""
