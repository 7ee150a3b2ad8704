"""`cubecloud view`: a trained scene in the browser (viser), with a clipping plane into the body."""
