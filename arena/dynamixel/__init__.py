"""Dynamixel X-series servos on Protocol 2.0 (the Koch arm's XL430-W250 and XL330-M288)."""
