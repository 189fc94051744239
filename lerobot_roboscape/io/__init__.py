"""Files that appear whole or not at all, and weights read only from safetensors that fit their model."""
