"""The generators' networks, one module each: ``conditioning`` (the condition images a generator sees and the
force's FiLM), ``gan`` (parts every GAN here shares: norms, noise dropout, initialisation, the PatchGAN
discriminator, the losses), ``unet`` (the multi-encoder U-Net of ``tn_cgan`` and ``lee``) and ``resnet``
(CycleGAN's ResNet generator and its image pool).

All images are [B, C, H, W] float tensors in [-1, 1].
"""
