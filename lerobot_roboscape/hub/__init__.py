"""The Hugging Face Hub round trip: cards (`cards.py`), pushing (`push.py`) and pulling (`pull.py`)."""
