"""Test configuration: float64 available, silent broadcasting turned into errors."""
import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
