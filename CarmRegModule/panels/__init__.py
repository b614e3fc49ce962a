"""Side panels of the workflow: data and geometry, landmarks, registration, result."""
