"""Control loops in Siemens-style units: digital PI with anti-windup, Kv conversions, feed-forward."""
