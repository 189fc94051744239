"""Files that appear whole or not at all (`atomic.py`), weights read only from safetensors that fit their model
(`weights.py`), and the Jinja renderer of the Hub cards and the reports (`templates.py`)."""
