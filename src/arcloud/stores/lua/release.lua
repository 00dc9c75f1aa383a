-- Release the keys still held with this token, waking their waiters. Needs leases.lua before it.
-- KEYS: the lock/claim keys. ARGV[1]: token. Returns how many were released.
local released = 0
for _, key in ipairs(KEYS) do
  released = released + release_lease(key, ARGV[1])
end
return released
