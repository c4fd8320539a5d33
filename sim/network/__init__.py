"""The network stand-in: the emulated 5G cell (uplink scheduler, UE buffers, delay line, traces, its
control API) and the emulated operator's CAMARA Quality-on-Demand API with its JSON Schemas."""
