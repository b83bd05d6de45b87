"""wfnn's learner maths: no network, clock, threads or files (a test keeps it so).

The two learners (the thesis' `WFNN` and the deep `DeepWFNN`) behind one interface
(`learners`), their networks, updates and compiled kernels, wire fitting, replay, exploration,
symmetries, the single-process architectures of Chapter 5, and the typed configs they share.
Files and the wire are `wfnn_io`'s; threads are the client's and the server's.
"""

__version__ = "0.1.0"
