//! Register addresses and bit values of the MPU-9250 (MPU-6500 die) and the AK8963
//! (research/hardware.md §1.3 and §1.5).

/// MPU-9250 registers and bits.
pub(super) mod mpu {
    /// Sample-rate divider: rate = internal rate / (1 + SMPLRT_DIV).
    pub(crate) const SMPLRT_DIV: u8 = 0x19;
    /// [2:0] DLPF_CFG (gyro and temperature low-pass filter).
    pub(crate) const CONFIG: u8 = 0x1A;
    /// [4:3] GYRO_FS_SEL, [1:0] FCHOICE_B.
    pub(crate) const GYRO_CONFIG: u8 = 0x1B;
    /// [4:3] ACCEL_FS_SEL.
    pub(crate) const ACCEL_CONFIG: u8 = 0x1C;
    /// [3] ACCEL_FCHOICE_B, [2:0] A_DLPF_CFG.
    pub(crate) const ACCEL_CONFIG2: u8 = 0x1D;
    /// Which registers each sample appends to the FIFO: [7] TEMP, [6:4] GYRO_X/Y/Z, [3] ACCEL,
    /// [0] SLV0.
    pub(crate) const FIFO_EN: u8 = 0x23;
    /// [6] WAIT_FOR_ES, [3:0] I2C_MST_CLK.
    pub(crate) const I2C_MST_CTRL: u8 = 0x24;
    /// [7] read, [6:0] the address SLV0 talks to on the auxiliary bus.
    pub(crate) const I2C_SLV0_ADDR: u8 = 0x25;
    /// The register SLV0 starts at.
    pub(crate) const I2C_SLV0_REG: u8 = 0x26;
    /// [7] I2C_SLV0_EN, [3:0] I2C_SLV0_LENG.
    pub(crate) const I2C_SLV0_CTRL: u8 = 0x27;
    /// [1] BYPASS_EN puts the AK8963 directly on the host bus.
    pub(crate) const INT_PIN_CFG: u8 = 0x37;
    /// [0] RAW_RDY_EN.
    pub(crate) const INT_ENABLE: u8 = 0x38;
    /// First of the 14 data bytes: accel xyz, temperature, gyro xyz (int16 big-endian).
    pub(crate) const ACCEL_XOUT_H: u8 = 0x3B;
    /// [6] FIFO_EN, [5] I2C_MST_EN (must be 0 for bypass), [2] FIFO_RST.
    pub(crate) const USER_CTRL: u8 = 0x6A;
    /// [7] H_RESET, [6] SLEEP, [2:0] CLKSEL.
    pub(crate) const PWR_MGMT_1: u8 = 0x6B;
    /// Per-axis standby bits.
    pub(crate) const PWR_MGMT_2: u8 = 0x6C;
    /// FIFO byte count, big-endian, FIFO_COUNTH then FIFO_COUNTL.
    pub(crate) const FIFO_COUNTH: u8 = 0x72;
    /// FIFO data: every byte read pops the FIFO (a burst stays at this register).
    pub(crate) const FIFO_R_W: u8 = 0x74;
    /// Identity: 0x71 (MPU-9250), 0x73 (MPU-9255).
    pub(crate) const WHO_AM_I: u8 = 0x75;

    /// PWR_MGMT_1.H_RESET: reset every register to its default.
    pub(crate) const H_RESET: u8 = 0x80;
    /// PWR_MGMT_1: awake, clock = auto-selected PLL.
    pub(crate) const CLKSEL_AUTO: u8 = 0x01;
    /// INT_PIN_CFG.BYPASS_EN.
    pub(crate) const BYPASS_EN: u8 = 0x02;
    /// INT_ENABLE.RAW_RDY_EN.
    pub(crate) const RAW_RDY_EN: u8 = 0x01;
    /// FIFO_EN.TEMP_OUT.
    pub(crate) const FIFO_EN_TEMP: u8 = 0x80;
    /// FIFO_EN.GYRO_XOUT | GYRO_YOUT | GYRO_ZOUT.
    pub(crate) const FIFO_EN_GYRO: u8 = 0x70;
    /// FIFO_EN.ACCEL.
    pub(crate) const FIFO_EN_ACCEL: u8 = 0x08;
    /// FIFO_EN.SLV_0: SLV0's EXT_SENS_DATA bytes.
    pub(crate) const FIFO_EN_SLV0: u8 = 0x01;
    /// USER_CTRL.FIFO_EN.
    pub(crate) const USER_FIFO_EN: u8 = 0x40;
    /// USER_CTRL.I2C_MST_EN: the MPU's I2C master drives the AK8963 (bypass then off).
    pub(crate) const USER_I2C_MST_EN: u8 = 0x20;
    /// USER_CTRL.FIFO_RST (self-clearing).
    pub(crate) const USER_FIFO_RST: u8 = 0x04;
    /// I2C_MST_CTRL.WAIT_FOR_ES: a sample waits for its external sensor data.
    pub(crate) const WAIT_FOR_ES: u8 = 0x40;
    /// I2C_MST_CTRL.I2C_MST_CLK = 13: 400 kHz.
    pub(crate) const I2C_MST_CLK_400KHZ: u8 = 0x0D;
    /// I2C_SLV0_ADDR bit 7: SLV0 reads.
    pub(crate) const SLV_READ: u8 = 0x80;
    /// I2C_SLV0_CTRL.I2C_SLV0_EN.
    pub(crate) const SLV_EN: u8 = 0x80;

    /// WHO_AM_I of an MPU-9250.
    pub(crate) const ID_MPU9250: u8 = 0x71;
    /// WHO_AM_I of an MPU-9255 (same register map).
    pub(crate) const ID_MPU9255: u8 = 0x73;
    /// WHO_AM_I of an MPU-6500: accel/gyro only, no magnetometer.
    pub(crate) const ID_MPU6500: u8 = 0x70;
}

/// AK8963 registers and bits.
pub(super) mod ak {
    /// Identity register, reads 0x48.
    pub(crate) const WIA: u8 = 0x00;
    /// Status 1: [0] DRDY, [1] DOR. First of the 8-byte block ST1, HXL..HZH, ST2.
    pub(crate) const ST1: u8 = 0x02;
    /// [4] BIT (16-bit output), [3:0] MODE.
    pub(crate) const CNTL1: u8 = 0x0A;
    /// [0] SRST soft reset.
    pub(crate) const CNTL2: u8 = 0x0B;
    /// First sensitivity-adjustment byte (ASAX, ASAY, ASAZ follow), fuse-ROM mode only.
    pub(crate) const ASAX: u8 = 0x10;

    /// WIA value.
    pub(crate) const ID: u8 = 0x48;
    /// ST1.DRDY: a new sample is in the data registers.
    pub(crate) const ST1_DRDY: u8 = 0x01;
    /// ST1.DOR: at least one sample was skipped since the last read.
    pub(crate) const ST1_DOR: u8 = 0x02;
    /// ST2.HOFL: magnetic sensor overflow, the sample is invalid.
    pub(crate) const ST2_HOFL: u8 = 0x08;
    /// ST2.BITM: mirror of CNTL1.BIT (set in 16-bit output mode).
    pub(crate) const ST2_BITM: u8 = 0x10;
    /// CNTL2.SRST.
    pub(crate) const SRST: u8 = 0x01;
    /// CNTL1 mode: power-down.
    pub(crate) const MODE_POWER_DOWN: u8 = 0x00;
    /// CNTL1 mode: fuse-ROM access.
    pub(crate) const MODE_FUSE_ROM: u8 = 0x0F;
    /// CNTL1 mode: continuous measurement 1 (8 Hz).
    pub(crate) const MODE_CONTINUOUS_1: u8 = 0x02;
    /// CNTL1 mode: continuous measurement 2 (100 Hz).
    pub(crate) const MODE_CONTINUOUS_2: u8 = 0x06;
    /// CNTL1.BIT: 16-bit output.
    pub(crate) const BIT_16: u8 = 0x10;
}
