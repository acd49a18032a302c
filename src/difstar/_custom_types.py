"""Array type aliases used across difstar (jaxtyping, checked at test time only)."""

from jaxtyping import Array, ArrayLike, Complex, Float, Int, Shaped

Scalar = Float[Array, ""]
ScalarLike = Float[ArrayLike, ""] | float
Image = Float[Array, "h w"]
ImageRGB = Float[Array, "3 h w"]

__all__ = ["Array", "ArrayLike", "Complex", "Float", "Int", "Shaped", "Scalar", "ScalarLike", "Image", "ImageRGB"]
