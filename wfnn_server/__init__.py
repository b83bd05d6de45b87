"""Think server of wfnn (replays experiences, publishes weights); see the project issues."""
