"""The stages of Algorithm 1 (DESIGN.md section 3), one module per step, each owning its
``[section]`` of the configuration. :class:`bftaichi.Reconstructor` runs them in order.

=====  ===========  =================================================================
step   module       what
=====  ===========  =================================================================
1      integrate    projective TSDF bootstrap (``[tsdf]``)
2      band         narrow band around the bootstrap surface, compacted (``[band]``)
3      observe      depth pixels -> SDF samples -> data term (``[observation]``)
4      prior        GMRF prior: membrane, curvature, anchors (``[prior]``)
5      solve        PCG MAP with the free-space active set (``[solver]``)
6      variance     probe estimate of ``diag(Q^-1)``, blended (``[solver]``)
6      misfit       the data's excess over the noise model, added (``observation.local_noise``)
7      surface      marching cubes and vertex sigma (``[mesh]``)
=====  ===========  =================================================================
"""
