"""Surface-only elastodynamic BEM (Sugimoto, Batty, Hachisuka): kernels, convolution quadrature, operators."""
