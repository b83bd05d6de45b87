"""wfnn's wire and files: the wire protocol, the Zenoh bus, segment files, persistence and experience logs.

Everything that crosses a process boundary lives here: `protocol` (frozen messages,
encode/decode, version, CRC, key expressions), `bus` (the `Bus` interface and its Zenoh
session), `segments` (CRC-framed append-only files), `persist` (versioned save/load and the one
atomic write), `logs` (experience logs; `logs_cli` is `wfnn-logs`) and `cli_errors` (bad input
ends in one line and a nonzero exit). The learner maths (`wfnn_common`) never imports it.
"""

from wfnn_io.launch import tool

main_logs = tool("wfnn_io.logs_cli")
"""`wfnn-logs`."""
