"""Streaming (paper 004): every tile resource moves disk → cache → memory → GPU and back.

- **cache**: the bytes a provider fetched (a gzipped quantized-mesh tile, a PNG), in RAM;
- **memory**: those bytes decoded into what the renderer uploads (a mesh, RGBA pixels);
- **GPU**: uploaded, owned by the renderer.

Each stage's object is made from the one before on worker threads and freed under that stage's
byte budget, least recently wanted first; the GPU stage never frees a tile drawn in the last
frame. Uploads happen on the GL thread, within a time slice per frame.

Requests come in three priority classes, the "three radii" of paper 004: what the frame on screen
wants (loads that block refinement come first: the selection orders them coarse to fine, near to
far), what the camera will want one second ahead along its velocity (decoded to memory), and what
it will want a few seconds ahead (fetched to the cache). Predicting along the velocity stretches
the radii ahead of the heading and shrinks them behind it; the selection of a higher camera
reaches farther, so they grow with altitude.

A clock decides when a job's result may be used. ``RealClock`` uses results when they are ready;
``SimClock`` (flights rendered offline) gives the workers the time they would have had in real
time at the requested frame rate, however long the offline frames take: a job's result is used
only once the simulated time passes its start (the simulated time its worker slot freed) plus
its cost. The cost is the source's declared one (``source.cost(key)``, seconds) where it has one,
else the worker thread's CPU time for the fetch and the decode: never wall time, so a loaded
machine (threads waiting for a core, the GIL) does not slow a simulated flight, and a source
with declared costs gives the same flight statistics on any machine. A simulated clock also
waits for a local job that has not finished in real time when its frame collects (it would have
had the time): when a result is usable is the clock's decision alone, not how soon this
machine's threads got to it. Network jobs (imagery layers) are not waited for.
"""

from lodscape.stream.streamer import (
    RealClock,
    SimClock,
    Streamer,
    StreamOptions,
    StreamStats,
)

__all__ = ["RealClock", "SimClock", "StreamOptions", "StreamStats", "Streamer"]
