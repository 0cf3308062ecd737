"""OPC UA server for the line (``station opcua``, ``station panel --opcua``): namespace ``urn:station``, object
``Station`` with the unit's state and the methods ``Start``/``Abort`` (docs/opcua.md)."""
