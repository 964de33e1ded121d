"""Node base class, graph model, launcher and supervisor."""
