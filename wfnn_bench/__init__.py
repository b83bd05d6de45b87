"""`wfnn-bench`: measured reproductions and speed figures (each prints a table, writes JSON/PNG)."""
