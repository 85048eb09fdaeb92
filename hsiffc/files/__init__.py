"""Helpers every layer may use, none of them hsiffc's physics: atomic writes that never
replace an input (:mod:`.atomic`), the output folder's lock (:mod:`.folderlock`) and JSON-safe
conversion of values (:mod:`.jsonsafe`). Private: their API may change without notice."""
