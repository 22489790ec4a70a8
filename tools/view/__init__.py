"""`tensortouch view`: a live local web page of what sensors publish (subscriber side)."""
