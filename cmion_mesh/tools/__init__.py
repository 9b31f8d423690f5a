"""Tools around a mesh: recording, replay, hz and echo, doctor, launch, demo, router."""
