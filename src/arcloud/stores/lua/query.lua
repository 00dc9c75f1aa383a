-- Objects indexed in a box of cells, with their bounds, in one round trip.
-- KEYS[1]: the map's bounds HASH. ARGV[1]: the map prefix, ARGV[2..7]: i0 i1 j0 j1 k0 k1, the inclusive
-- ranges of cell indices (the caller bounds their product), ARGV[8]: cells per object above which
-- reading every object's bounds is cheaper than reading the cells (a small map, a large box).
-- Returns a flat list id1, bounds1, id2, bounds2, ... (bounds: 6 packed float64); the caller tests them.
local BATCH = 1000  -- keep unpack() below Lua's stack limit
local prefix = ARGV[1] .. ':cell:'
local i0, i1, j0, j1, k0, k1 = tonumber(ARGV[2]), tonumber(ARGV[3]), tonumber(ARGV[4]), tonumber(ARGV[5]), tonumber(ARGV[6]), tonumber(ARGV[7])
local n_cells = (i1 - i0 + 1) * (j1 - j0 + 1) * (k1 - k0 + 1)
if n_cells > tonumber(ARGV[8]) * redis.call('HLEN', KEYS[1]) then
  return redis.call('HGETALL', KEYS[1])
end
local ids, seen, cell_keys = {}, {}, {}

local function union(keys)
  for _, id in ipairs(redis.call('SUNION', unpack(keys))) do
    if not seen[id] then
      seen[id] = true
      ids[#ids + 1] = id
    end
  end
end

for i = i0, i1 do
  for j = j0, j1 do
    local row = prefix .. i .. ':' .. j .. ':'
    for k = k0, k1 do
      cell_keys[#cell_keys + 1] = row .. k
      if #cell_keys == BATCH then
        union(cell_keys)
        cell_keys = {}
      end
    end
  end
end
if #cell_keys > 0 then
  union(cell_keys)
end

local out = {}
for first = 1, #ids, BATCH do
  local batch = {}
  for n = first, math.min(first + BATCH - 1, #ids) do
    batch[#batch + 1] = ids[n]
  end
  local bounds = redis.call('HMGET', KEYS[1], unpack(batch))
  for n, id in ipairs(batch) do
    if bounds[n] then
      out[#out + 1] = id
      out[#out + 1] = bounds[n]
    end
  end
end
return out
