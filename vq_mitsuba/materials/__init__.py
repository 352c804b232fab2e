"""Material fields: what the networks are (training lives in vq_mitsuba.fit)."""
