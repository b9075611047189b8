"""The long-running twin: the engine paced to the wall clock, on Zenoh, with excitations."""
