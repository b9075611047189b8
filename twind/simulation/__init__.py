"""Fixed-step time-domain engine of suspensions plus damping loops at the CDS model rate."""
