"""What a fit minimises: the likelihood of the camera's samples, the paper's loss and its variants."""
