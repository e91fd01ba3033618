"""The spatial soft arm (four PCC segments, two bending coordinates each, under gravity)."""
