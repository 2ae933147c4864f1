"""Into the plant: MQTT publishing to the plant's broker and the OPC UA server for the cell's PLC."""
