"""Bridges to other training libraries; each imports its backend lazily and names the extra to install."""
