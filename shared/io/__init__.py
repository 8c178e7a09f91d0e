"""Input and output: laser logs and map files, the wire format of the bus messages, the Zenoh bus
and its configuration, MCAP recordings, fleet security and the map_server output."""
