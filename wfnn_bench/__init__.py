"""`wfnn-bench`: measured reproductions and speed figures (each prints a table, writes JSON/PNG)."""

from wfnn_io.launch import tool

main = tool("wfnn_bench.cli")
"""`wfnn-bench`."""
main_wfnn = tool("wfnn_bench.report")
"""`wfnn` (`wfnn report`)."""
