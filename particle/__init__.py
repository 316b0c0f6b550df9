"""Real-time particle model: one particle per vertex, one Maxwell-Solid connector per edge."""
