"""Loop closure: place recognition, candidates, geometric verification, acceptance, retraction."""
