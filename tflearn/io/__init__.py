"""File formats: basis.json (the learned model, readable without tflearn)."""
